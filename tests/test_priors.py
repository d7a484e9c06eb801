"""Prior collection (determinism, resume after SIGKILL, Ray), dataset checks,
training, checkpoints. Collection runs on a coarse cloth with short episodes."""

import json
import os
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest
import torch
from fabric_imitation.learning.dataset import LoadDataset, ShardEpisodes
from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.priors import load_priors
from fabric_imitation.learning.train import TrainConfig, _split, train_priors
from fabric_imitation.scenarios.loader import LoadScenario
from fabric_imitation.tools.collect import Collect

TINY = (
    "cloth: {resolution: [5, 5, 2]}\n"
    "collection: {episode_length: 4, max_warmup_steps: 1}\n"
)


def tiny_scenario():
    return LoadScenario(scenario_name="prior", scenario_text=TINY)


def collect(path, n, workers=1, executor="local"):
    return Collect(
        scenario=tiny_scenario(),
        scenario_name="prior",
        transitions=n,
        out=path,
        workers=workers,
        executor=executor,
        show_progress=False,
    )


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "one.h5"
    summary = collect(path, 12, workers=1)
    assert summary["transitions"] == 12 and summary["complete"]
    return path


def _arrays(path):
    with h5py.File(path, "r") as f:
        return {k: f[k][:] for k in f}


@pytest.mark.slow
def test_two_workers_collect_the_same_data_as_one(tiny_dataset, tmp_path):
    two = tmp_path / "two.h5"
    collect(two, 12, workers=2)
    a, b = _arrays(tiny_dataset), _arrays(two)
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_dataset_holds_what_a_transition_needs(tiny_dataset):
    ds = LoadDataset(tiny_dataset)
    assert len(ds) == 12
    assert ds.arrays["mask"].shape == (12, 160, 160)
    assert (
        ds.arrays["keypoints"].shape == ds.arrays["keypoints_next"].shape == (12, 8, 3)
    )
    assert np.abs(ds.arrays["action"]).max() <= 0.03 + 1e-6
    for key in ("scenario_yaml", "seed", "code_version", "camera", "fingerprint"):
        assert key in ds.attrs
    # Consecutive transitions of an episode chain: S' of one is S of the next.
    e, s = ds.arrays["episode"], ds.arrays["step"]
    same = (e[1:] == e[:-1]) & (s[1:] == s[:-1] + 1)
    np.testing.assert_allclose(
        ds.arrays["keypoints_next"][:-1][same], ds.arrays["keypoints"][1:][same]
    )


@pytest.mark.slow
def test_collection_killed_with_sigkill_resumes_to_exactly_n(tiny_dataset, tmp_path):
    out = tmp_path / "killed.h5"
    cmd = [
        sys.executable,
        "-m",
        "fabric_imitation.tools.cli",
        "collect",
        "--scenario",
        "prior",
        "--scenario_text",
        TINY,
        "--transitions",
        "12",
        "--out",
        str(out),
        "--workers",
        "1",
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while time.time() < deadline and not ShardEpisodes(out):
        time.sleep(0.2)
    time.sleep(0.3)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not out.exists() or not LoadDataset(out).attrs["complete"]
    result = subprocess.run(
        cmd + ["--json"], capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["transitions"] == 12 and summary["resumed"]
    a, b = _arrays(tiny_dataset), _arrays(out)
    pairs = set(zip(b["episode"].tolist(), b["step"].tolist(), strict=True))
    assert len(pairs) == 12  # unique
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@pytest.mark.slow
def test_ray_executor_collects_the_same_data(tiny_dataset, tmp_path):
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        out = tmp_path / "ray.h5"
        collect(out, 12, workers=2, executor="ray")
    finally:
        ray.shutdown()
    a, b = _arrays(tiny_dataset), _arrays(out)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_bad_datasets_are_reported(tiny_dataset, tmp_path):
    with pytest.raises(InputError, match="not found"):
        LoadDataset(tmp_path / "none.h5")
    truncated = tmp_path / "truncated.h5"
    truncated.write_bytes(tiny_dataset.read_bytes()[:5000])
    with pytest.raises(InputError, match="corrupt or truncated"):
        LoadDataset(truncated)
    nan = tmp_path / "nan.h5"
    nan.write_bytes(tiny_dataset.read_bytes())
    with h5py.File(nan, "r+") as f:
        f["action"][3] = np.nan
    with pytest.raises(InputError, match="NaN or inf in action of transition 3"):
        LoadDataset(nan)
    empty = tmp_path / "empty.h5"
    empty.write_bytes(tiny_dataset.read_bytes())
    with h5py.File(empty, "r+") as f:
        for k in list(f):
            f[k].resize(0, axis=0)
    with pytest.raises(InputError, match="empty"):
        LoadDataset(empty)
    # Resuming into a dataset of another scenario is refused.
    other = LoadScenario(scenario_name="prior", scenario_text=TINY + "random_seed: 3\n")
    with pytest.raises(InputError, match="another"):
        Collect(
            scenario=other,
            scenario_name="prior",
            transitions=20,
            out=tiny_dataset,
            show_progress=False,
        )


@pytest.fixture(scope="session")
def tiny_priors(tiny_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("priors")
    summary = train_priors(
        data=tiny_dataset,
        out=out,
        progress=False,
        config=TrainConfig(epochs=60, keypoint_epochs=3, holdout_fraction=0.2),
    )
    return out, summary


@pytest.mark.slow
def test_training_overfits_a_tiny_dataset(tiny_dataset, tmp_path):
    out = tmp_path / "p"
    train_priors(
        data=tiny_dataset,
        out=out,
        progress=False,
        config=TrainConfig(epochs=1500, keypoint_epochs=0, holdout_fraction=0.1),
    )
    priors = load_priors(out)
    ds = LoadDataset(tiny_dataset, images=False)
    train_idx, _ = _split(ds, 0.1, 0)  # the transitions it was trained on
    S, Sn, A = (
        torch.as_tensor(ds.arrays[k][train_idx])
        for k in ("keypoints", "keypoints_next", "action")
    )
    fd = (priors.forward(S, A) - Sn).norm(dim=-1).mean()
    still = (S - Sn).norm(dim=-1).mean()
    assert fd < 0.25 * still
    fi = (priors.inverse(S, Sn) - A).abs().mean()
    assert fi < 0.25 * A.abs().mean()
    assert (out / "curves.png").stat().st_size > 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert {"f_D_ratio", "f_I_ratio", "keypoint_error_mm"} <= metrics.keys()


def test_checkpoint_round_trip_is_exact(tiny_priors, tiny_dataset, tmp_path):
    """Networks in memory (the trained ones with every weight changed, so
    nothing can come from the first file) against their reload."""
    out, _ = tiny_priors
    a = load_priors(out)
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for net in (a.f_R, a.f_D, a.f_I):
            for value in net.state_dict().values():
                if value.is_floating_point():
                    value.add_(0.01 * torch.randn(value.shape, generator=gen))
    a.save(tmp_path / "copy", extra={"prior_states": a.prior_states, "note": "x"})
    b = load_priors(tmp_path / "copy")
    for name in ("f_R", "f_D", "f_I"):
        mine, theirs = getattr(a, name).state_dict(), getattr(b, name).state_dict()
        assert mine.keys() == theirs.keys()
        for k in mine:
            torch.testing.assert_close(mine[k], theirs[k], rtol=0, atol=0)
    ds = LoadDataset(tiny_dataset)
    S, A = ds.arrays["keypoints"][:5], ds.arrays["action"][:5]
    torch.testing.assert_close(a.forward(S, A), b.forward(S, A), rtol=0, atol=0)
    torch.testing.assert_close(a.inverse(S, S), b.inverse(S, S), rtol=0, atol=0)
    from fabric_imitation.learning.dataset import DecodeDepth

    depth = DecodeDepth(ds.arrays["depth"][:3])
    np.testing.assert_array_equal(
        a.keypoints(ds.arrays["mask"][:3], depth),
        b.keypoints(ds.arrays["mask"][:3], depth),
    )
    assert b.prior_states.shape[1:] == (8, 3)
    assert b.metadata["note"] == "x"


class _RunsCode:
    """Unpickling this calls `touch` on a file (what an attack would do)."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (subprocess.call, (["touch", self.path],))


def test_a_checkpoint_that_would_run_code_is_refused(tiny_priors, tmp_path):
    import hashlib
    import shutil

    out, _ = tiny_priors
    bad = tmp_path / "bad"
    shutil.copytree(out, bad)
    witness = tmp_path / "code-ran"
    tensors = torch.load(bad / "priors.pt", weights_only=True)
    tensors["payload"] = _RunsCode(witness)
    torch.save(tensors, bad / "priors.pt")
    description = json.loads((bad / "priors.json").read_text())
    description["tensors"]["sha256"] = hashlib.sha256(
        (bad / "priors.pt").read_bytes()
    ).hexdigest()
    (bad / "priors.json").write_text(json.dumps(description))
    with pytest.raises(InputError, match="need pickle"):
        load_priors(bad)
    assert not witness.exists()
    # An old pickled checkpoint (no priors.json) is not even opened.
    (bad / "priors.json").unlink()
    with pytest.raises(InputError, match="old pickled checkpoint"):
        load_priors(bad)
    assert not witness.exists()


def test_a_changed_tensors_file_fails_its_checksum(tiny_priors, tmp_path):
    import shutil

    out, _ = tiny_priors
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    data = bytearray((copy / "priors.pt").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (copy / "priors.pt").write_bytes(bytes(data))
    with pytest.raises(InputError, match="checksum mismatch"):
        load_priors(copy)


def test_mismatched_checkpoints_raise(tiny_priors, tmp_path):
    out, _ = tiny_priors
    with pytest.raises(InputError, match="predict 8 keypoints, the scenario uses 12"):
        load_priors(out, num_keypoints=12)
    with pytest.raises(InputError, match=r"\(120, 160\)"):
        load_priors(out, image_size=(120, 160))
    scenario = LoadScenario(
        scenario_name="box",
        scenario_text="camera: {width: 160, height: 160, focal: !FovDegrees {y: 40.0}}",
    )
    from fabric_imitation.diagrams.station import CameraModelFromConfig

    with pytest.raises(InputError, match="another camera"):
        load_priors(out, camera=CameraModelFromConfig(scenario.camera))
    (tmp_path / "priors.json").write_text("{not json")
    with pytest.raises(InputError, match="corrupt"):
        load_priors(tmp_path)
    with pytest.raises(InputError, match="not found"):
        load_priors(tmp_path / "nowhere")


@pytest.fixture(scope="session")
def tiny_contact_dataset(tmp_path_factory):
    """The tiny prior scene with a tall box in the cloth's way, the drift
    carrying the cloth up and over it."""
    path = tmp_path_factory.mktemp("contact") / "box.h5"
    scenario = LoadScenario(
        scenario_name="prior",
        scenario_text=TINY
        + "object: {kind: box, size: [0.17, 0.02, 0.20], pose: [0.0, -0.14, 0.0]}\n"
        + "collection: {episode_length: 4, max_warmup_steps: 1, "
        "drift_lower: [0.0, -0.03, 0.0], drift_upper: [0.0, -0.03, 0.0]}\n",
    )
    Collect(
        scenario=scenario,
        scenario_name="prior",
        transitions=12,
        out=path,
        show_progress=False,
    )
    return path, scenario


def test_collection_beside_an_object_keeps_the_hands_out_of_it(
    tiny_contact_dataset,
):
    """With an object the collector judges rule 4 in the object's frame on
    the grasped points and the hands' spheres: no recorded gripper comes
    nearer the board than its margins, although every episode's drift runs
    straight at it (the object is 21 cm from the grasped corners)."""
    from fabric_imitation.learning.object_shape import object_signed_distance
    from fabric_imitation.learning.state import world_to_object
    from fabric_imitation.tasks.referee import HandSpheres

    path, scenario = tiny_contact_dataset
    ds = LoadDataset(path, images=False)
    assert len(ds) == 12
    pose = np.array([0.0, -0.14, 0.0])
    grippers = world_to_object(ds.arrays["grippers_next"], pose)
    spheres = HandSpheres(scenario)
    points = grippers[..., None, :] + spheres[:, :3]
    distance = object_signed_distance(
        torch.as_tensor(points), "box", torch.as_tensor(scenario.object.size)
    ).numpy()
    clearance = distance - spheres[:, 3]
    assert clearance.min() >= scenario.safety.hand_margin - 1e-6
    # The drift did bring the grippers towards the board (y falls).
    assert grippers[..., 1].min() < grippers[0, :, 1].min() - 0.05


def test_forward_only_training_keeps_f_R_and_f_I(
    tiny_priors, tiny_dataset, tiny_contact_dataset, tmp_path
):
    """`train --forward-only`: f_D learns both datasets from a fresh start;
    f_R, f_I, the normalisers and the prior states are the base's, bit for
    bit; the held-out errors are reported per dataset."""
    from fabric_imitation.learning.train import train_forward

    base, _ = tiny_priors
    out = tmp_path / "fo"
    summary = train_forward(
        data=[tiny_dataset, tiny_contact_dataset[0]],
        base=base,
        out=out,
        progress=False,
        config=TrainConfig(epochs=5, holdout_fraction=0.2),
    )
    old, new = load_priors(base), load_priors(out)
    for name in ("f_R", "f_I"):
        for (k, a), (_, b) in zip(
            getattr(old, name).state_dict().items(),
            getattr(new, name).state_dict().items(),
            strict=True,
        ):
            assert torch.equal(a, b), (name, k)
    for k in old.norms:
        assert torch.equal(old.norms[k].mean, new.norms[k].mean)
    assert torch.equal(old.prior_states, new.prior_states)
    changed = [
        not torch.equal(a, b)
        for a, b in zip(
            old.f_D.state_dict().values(), new.f_D.state_dict().values(), strict=True
        )
    ]
    assert all(changed)
    rows = summary["f_D_held_out"]
    assert [r["dataset"] for r in rows] == [
        str(tiny_dataset),
        str(tiny_contact_dataset[0]),
    ]
    assert all(r["heldout_transitions"] > 0 for r in rows)
    with pytest.raises(InputError, match="at least one --data"):
        train_forward(data=[], base=base, out=tmp_path / "none", progress=False)
