"""`demo import` on small generated recordings: a top-down RGB-D camera
sees a green cloth slide over a box with an ArUco marker on its top and an
operator's (skin-coloured) hands at the near corners. The import must
rebuild the cloth's masks and the object's pose from the files alone; each
bad input gets a one-line error and leaves no demo directory behind."""

import math
import subprocess
import sys

import cv2
import numpy as np
import pytest
from fabric_imitation.diagrams.station import (
    MARKER_MARGIN_CELLS,
    CameraModelFromConfig,
    MarkerTexture,
    RawCameraConfig,
)
from fabric_imitation.learning.demo_import import (
    ReadBag,
    ReadRecording,
    WriteRawRecording,
)
from fabric_imitation.learning.demo_io import LoadDemo
from fabric_imitation.learning.errors import InputError
from fabric_imitation.scenarios.loader import LoadScenario
from fabric_imitation.tools.demo_record import ImportDemoForScenario

SCALE = 4  # the recording is 4x the control camera's 160 px, as export-raw
POSE = (0.03, -0.12, 25.0)  # the object's true pose [m, m, deg]
HSV = ((45, 80, 40), (90, 255, 255))
TABLE, BOX, GREEN, SKIN = (184, 143, 102), (64, 89, 191), (38, 158, 77), (222, 168, 138)


def _scenario():
    return LoadScenario(
        scenario_name="box_capture",
        scenario_text=f"object: {{pose: {list(POSE)}, marker: {{id: 7, size: 0.06, "
        "offset: [0.0, 0.0, 0.06, 0.0]}}",
    )


def _object_to_world(p_O, pose=POSE):
    c, s = math.cos(math.radians(pose[2])), math.sin(math.radians(pose[2]))
    p = np.asarray(p_O, float)
    return np.c_[
        pose[0] + c * p[:, 0] - s * p[:, 1],
        pose[1] + s * p[:, 0] + c * p[:, 1],
        p[:, 2],
    ]


TABLE_MARKER = {"id": 3, "size": 0.08, "pose": [-0.25, 0.28, 10.0]}


def synthetic_recording(frames=12, release_at=None, table_marker=False):
    """Frames, depths [m], true masks and the raw camera's intrinsics. The
    hands (3 cm above the cloth's near corners) carry it; from frame
    `release_at` on they stay where they let go while the cloth slides on.
    With `table_marker`, TABLE_MARKER lies on the table too."""
    scenario = _scenario()
    cam = CameraModelFromConfig(RawCameraConfig(scenario, SCALE))
    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
    X_CW = np.linalg.inv(cam.X_WC)

    def project(P_W):
        p = (X_CW[:3, :3] @ np.asarray(P_W, float).T).T + X_CW[:3, 3]
        uv = (K @ p.T).T
        return uv[:, :2] / uv[:, 2:3]

    def poly(P_W):
        return np.round(project(P_W) * 16).astype(np.int32)

    marker = scenario.object.marker
    texture = cv2.cvtColor(
        cv2.imread(str(MarkerTexture(marker.dictionary, marker.id))), cv2.COLOR_BGR2RGB
    )
    cells = 6
    side = marker.size * (cells + 2 * MARKER_MARGIN_CELLS) / cells
    h = side / 2
    # The texture's top-left is the plaque's (-x, +y) corner (as Drake draws it).
    plaque = _object_to_world(
        [[-h, h, 0.06], [h, h, 0.06], [h, -h, 0.06], [-h, -h, 0.06]]
    )
    box = _object_to_world(
        [
            [-0.07, 0.045, 0.06],
            [0.07, 0.045, 0.06],
            [0.07, -0.045, 0.06],
            [-0.07, -0.045, 0.06],
        ]
    )
    rgb, depth, masks = [], [], []
    W = H = cam.width
    for k in range(frames):
        image = np.zeros((H, W, 3), np.uint8)
        image[:] = TABLE
        d = np.full((H, W), 1.0, np.float32)
        cv2.fillPoly(image, [poly(box)], BOX, shift=4)
        top = np.zeros((H, W), np.uint8)
        cv2.fillPoly(top, [poly(box)], 1, shift=4)
        d[top > 0] = 0.94
        if table_marker:
            t = TABLE_MARKER
            sheet = cv2.cvtColor(
                cv2.imread(str(MarkerTexture(marker.dictionary, t["id"]))),
                cv2.COLOR_BGR2RGB,
            )
            g = t["size"] * (cells + 2 * MARKER_MARGIN_CELLS) / cells / 2
            corners = _object_to_world(
                [[-g, g, 0.0], [g, g, 0.0], [g, -g, 0.0], [-g, -g, 0.0]], t["pose"]
            )
            sw, sh = sheet.shape[1], sheet.shape[0]
            M = cv2.getPerspectiveTransform(
                np.float32([[0, 0], [sw, 0], [sw, sh], [0, sh]]),
                np.float32(project(corners)),
            )
            on = cv2.warpPerspective(np.ones((sh, sw), np.uint8), M, (W, H)) > 0
            image[on] = cv2.warpPerspective(sheet, M, (W, H))[on]
        tw, th = texture.shape[1], texture.shape[0]
        M = cv2.getPerspectiveTransform(
            np.float32([[0, 0], [tw, 0], [tw, th], [0, th]]),
            np.float32(project(plaque)),
        )
        warped = cv2.warpPerspective(texture, M, (W, H))
        inside = cv2.warpPerspective(np.ones((th, tw), np.uint8), M, (W, H)) > 0
        image[inside] = warped[inside]
        # The cloth slides from the far side over the box, 2 cm a frame.
        y0 = 0.15 - 0.02 * k
        cloth = np.array(
            [
                [-0.15, y0 - 0.15, 0.004],
                [0.15, y0 - 0.15, 0.004],
                [0.15, y0 + 0.15, 0.004],
                [-0.15, y0 + 0.15, 0.004],
            ]
        )
        mask = np.zeros((H, W), np.uint8)
        cv2.fillPoly(mask, [poly(cloth)], 1, shift=4)
        image[mask > 0] = GREEN
        d[mask > 0] = 0.996
        held = y0 if release_at is None else 0.15 - 0.02 * min(k, release_at)
        for x in (-0.15, 0.15):
            centre = np.round(project([[x, held - 0.15, 0.034]])[0]).astype(int)
            hand = np.zeros((H, W), np.uint8)
            cv2.circle(hand, tuple(centre.tolist()), 9 * SCALE, 1, -1)
            image[hand > 0] = SKIN
            d[hand > 0] = 0.966
            mask[hand > 0] = 0
        rgb.append(image)
        depth.append(d)
        masks.append(mask)
    intrinsics = {
        "width": W,
        "height": H,
        "fx": cam.fx,
        "fy": cam.fy,
        "cx": cam.cx,
        "cy": cam.cy,
    }
    return rgb, depth, np.stack(masks), intrinsics


@pytest.fixture(scope="module")
def raw(tmp_path_factory):
    out = tmp_path_factory.mktemp("rec") / "raw"
    rgb, depth, masks, intrinsics = synthetic_recording()
    WriteRawRecording(out, rgb=rgb, depth=depth, fps=15.0, intrinsics=intrinsics)
    return out, masks


def _import(raw_dir, out, hsv=HSV, **kwargs):
    recording = ReadRecording(
        raw_dir / "rgb.mp4", raw_dir / "depth", raw_dir / "intrinsics.yaml"
    )
    return ImportDemoForScenario(
        recording=recording,
        scenario=_scenario(),
        scenario_name="box_capture",
        out=out,
        hsv=None if "masks" in kwargs else hsv,
        **kwargs,
    )


def _small(mask):
    return (
        cv2.resize(mask.astype(np.float32), (160, 160), interpolation=cv2.INTER_AREA)
        >= 0.5
    )


def test_import_rebuilds_the_masks_and_the_marker_pose(raw, tmp_path):
    raw_dir, true_masks = raw
    summary = _import(raw_dir, tmp_path / "demo")
    demo = LoadDemo(tmp_path / "demo")
    frames = summary["subsampling"]["frames"]
    assert len(frames) == demo.num_frames >= 3
    for k, mask in zip(frames, demo.mask, strict=True):
        truth = _small(true_masks[k])
        iou = (truth & (mask > 0)).sum() / (truth | (mask > 0)).sum()
        assert iou >= 0.9, (k, iou)
    x, y, yaw = demo.object_pose
    assert math.hypot(x - POSE[0], y - POSE[1]) < 0.005, demo.object_pose
    assert abs(math.degrees(yaw) - POSE[2]) < 2.0, demo.object_pose
    # The cloth slides over the marker: later frames lose it, and say so.
    assert summary["marker"]["frames_missing"] > 0
    assert not (tmp_path / "demo" / "ground_truth.npz").exists()
    assert demo.manifest["source"] == "import"


def _bag(path, rgb, depth, intrinsics, *, topics=("/c", "/d", "/i"), ros=2):
    """Writes a ROS `ros` (1: a .bag file, 2: a bag directory) bag as a
    camera driver records one."""
    from rosbags.typesys import Stores, get_typestore

    if ros == 1:
        from rosbags.rosbag1 import Writer

        store = get_typestore(Stores.ROS1_NOETIC)
        serialize = store.serialize_ros1
        open_writer = Writer(path)
    else:
        from rosbags.rosbag2 import Writer

        store = get_typestore(Stores.ROS2_HUMBLE)
        serialize = store.serialize_cdr
        open_writer = Writer(path, version=8)
    Image = store.types["sensor_msgs/msg/Image"]
    Info = store.types["sensor_msgs/msg/CameraInfo"]
    Header = store.types["std_msgs/msg/Header"]
    Time = store.types["builtin_interfaces/msg/Time"]
    Roi = store.types["sensor_msgs/msg/RegionOfInterest"]
    with open_writer as writer:
        conns = [
            writer.add_connection(t, m, typestore=store)
            for t, m in zip(
                topics,
                (Image.__msgtype__, Image.__msgtype__, Info.__msgtype__),
                strict=True,
            )
        ]
        W, H = intrinsics["width"], intrinsics["height"]
        for k, (c, d) in enumerate(zip(rgb, depth, strict=True)):
            ns = int(k * 1e9 / 15)
            stamp = Time(sec=ns // 10**9, nanosec=ns % 10**9)
            header = (
                Header(seq=k, stamp=stamp, frame_id="cam")
                if ros == 1
                else Header(stamp=stamp, frame_id="cam")
            )
            color = Image(
                header=header,
                height=H,
                width=W,
                encoding="rgb8",
                is_bigendian=0,
                step=3 * W,
                data=np.ascontiguousarray(c).ravel(),
            )
            mm = np.round(np.asarray(d) * 1000).astype(np.uint16)
            dep = Image(
                header=header,
                height=H,
                width=W,
                encoding="16UC1",
                is_bigendian=0,
                step=2 * W,
                data=mm.view(np.uint8).ravel(),
            )
            writer.write(conns[0], ns, serialize(color, Image.__msgtype__))
            writer.write(conns[1], ns, serialize(dep, Image.__msgtype__))
            if k == 0:
                K = [
                    intrinsics["fx"],
                    0,
                    intrinsics["cx"],
                    0,
                    intrinsics["fy"],
                    intrinsics["cy"],
                    0,
                    0,
                    1,
                ]
                # ROS 1 spells the matrices in capitals.
                matrices = {
                    "d": np.zeros(5),
                    "k": np.array(K, float),
                    "r": np.eye(3).ravel(),
                    "p": np.zeros(12),
                }
                if ros == 1:
                    matrices = {key.upper(): v for key, v in matrices.items()}
                info = Info(
                    header=header,
                    height=H,
                    width=W,
                    distortion_model="plumb_bob",
                    **matrices,
                    binning_x=0,
                    binning_y=0,
                    roi=Roi(
                        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
                    ),
                )
                writer.write(conns[2], ns, serialize(info, Info.__msgtype__))


@pytest.mark.parametrize("ros", [1, 2])
def test_a_ros_bag_round_trips(tmp_path, ros):
    pytest.importorskip("rosbags")
    rgb, depth, _, intrinsics = synthetic_recording(frames=6)
    bag = tmp_path / ("run.bag" if ros == 1 else "bag")
    _bag(bag, rgb, depth, intrinsics, ros=ros)
    rec = ReadBag(bag, color_topic="/c", depth_topic="/d", info_topic="/i")
    assert rec.rgb.shape == (6, 160 * SCALE, 160 * SCALE, 3)
    np.testing.assert_array_equal(rec.rgb[3], rgb[3])
    np.testing.assert_allclose(rec.depth[3], depth[3], atol=1e-3)
    assert rec.intrinsics["fx"] == pytest.approx(intrinsics["fx"])
    assert rec.fps == pytest.approx(15.0, rel=1e-3)
    with pytest.raises(InputError, match="has no topic /nope"):
        ReadBag(bag, color_topic="/nope", depth_topic="/d", info_topic="/i")


def _cli(*args):
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "fabric_imitation.tools.cli",
            "demo",
            "import",
            *map(str, args),
        ],
        capture_output=True,
        text=True,
    )


def test_bad_recordings_get_one_line_errors_and_no_demo(raw, tmp_path):
    """Two through the command line (exit status 2, one line), the rest
    through the same functions in this process."""
    import shutil

    import yaml
    from fabric_imitation.learning.demo_io import WriteVideo

    raw_dir, _ = raw
    bad = tmp_path / "bad"
    shutil.copytree(raw_dir, bad)
    out = tmp_path / "demo"
    common = [
        "--scenario",
        "box_capture",
        "--out",
        out,
        "--rgb",
        bad / "rgb.mp4",
        "--depth",
        bad / "depth",
        "--intrinsics",
        bad / "intrinsics.yaml",
        "--fabric-hsv",
        *HSV[0],
        *HSV[1],
    ]

    def no_demo():
        assert not out.exists() and not list(tmp_path.glob("demo.partial*"))

    def cli_fails(pattern, *extra):
        result = _cli(*common, *extra)
        assert result.returncode == 2, result.stderr
        lines = result.stderr.strip().splitlines()
        assert lines[-1].startswith("fabric-imitate: error: "), result.stderr
        assert pattern in lines[-1], result.stderr
        no_demo()

    def fails(pattern, **kwargs):
        with pytest.raises(InputError, match=pattern):
            _import(bad, out, **kwargs)
        no_demo()

    # The scenario's marker (id 7) is found; another id is in no frame.
    cli_fails("marker 3 (DICT_4X4_50) found in no frame", "--marker-id", "3")
    # Depth with a frame fewer than the video.
    last = sorted((bad / "depth").iterdir())[-1]
    moved = tmp_path / last.name
    last.rename(moved)
    cli_fails("has 12 frames, depth")
    moved.rename(last)
    # A colour box that catches nothing; a mask video that covers everything.
    with pytest.raises(InputError, match="the fabric mask is empty in"):
        _import(bad, out, hsv=((150, 200, 200), (160, 255, 255)))
    no_demo()
    white = [np.full((160 * SCALE,) * 2 + (3,), 255, np.uint8)] * 12
    WriteVideo(tmp_path / "masks.mp4", white, 15)
    from fabric_imitation.learning.demo_import import ReadVideo

    white = ReadVideo(tmp_path / "masks.mp4")[0].max(axis=3) > 127
    fails("covers the whole image", masks=white)
    # Depth of another size.
    first = sorted((bad / "depth").iterdir())[0]
    original = first.read_bytes()
    cv2.imwrite(str(first), np.zeros((10, 10), np.uint16))
    fails("differ in size")
    first.write_bytes(original)
    # Intrinsics without fx, for another image size, or not the scenario's.
    good = (bad / "intrinsics.yaml").read_text()
    k = yaml.safe_load(good)
    (bad / "intrinsics.yaml").write_text(
        yaml.safe_dump({x: v for x, v in k.items() if x != "fx"})
    )
    fails("missing fx")
    (bad / "intrinsics.yaml").write_text(yaml.safe_dump({**k, "width": 999}))
    fails(f"are for 999 x {160 * SCALE} images")
    (bad / "intrinsics.yaml").write_text(yaml.safe_dump({**k, "fx": k["fx"] * 1.5}))
    fails("do not match the scenario's camera")
    (bad / "intrinsics.yaml").write_text(good)
    # A bag that is not there.
    with pytest.raises(InputError, match="bag not found"):
        ReadBag(
            tmp_path / "none.bag", color_topic="/c", depth_topic="/d", info_topic="/i"
        )


def test_the_demo_ends_when_the_hands_stop_moving_the_cloth(tmp_path):
    """Frames after the operator's hands stop (the cloth settling on) are not
    demo steps; the last recorded frame stays the final observation."""
    rgb, depth, _, intrinsics = synthetic_recording(frames=18, release_at=9)
    WriteRawRecording(
        tmp_path / "raw", rgb=rgb, depth=depth, fps=15.0, intrinsics=intrinsics
    )
    summary = _import(tmp_path / "raw", tmp_path / "demo")
    sub = summary["subsampling"]
    assert sub["still_frames_dropped"]["by"] == "the hands on the fabric"
    assert sub["frames"] == [0, 3, 6, 9], sub
    assert sub["final_frame"] == 17


def test_a_marker_on_the_table_gives_the_camera_pose(tmp_path):
    from fabric_imitation.learning.demo_import import (
        CameraPoseFromTableMarker,
        DetectMarker,
    )

    rgb, depth, _, intrinsics = synthetic_recording(frames=4, table_marker=True)
    truth = CameraModelFromConfig(RawCameraConfig(_scenario(), SCALE))
    K = np.array(
        [
            [intrinsics["fx"], 0, intrinsics["cx"]],
            [0, intrinsics["fy"], intrinsics["cy"]],
            [0, 0, 1],
        ]
    )
    corners = DetectMarker(rgb[0], "DICT_4X4_50", TABLE_MARKER["id"])
    X_WC = CameraPoseFromTableMarker(
        corners, K, TABLE_MARKER["size"], TABLE_MARKER["pose"], depth=depth[0]
    )
    assert np.linalg.norm(X_WC[:3, 3] - truth.X_WC[:3, 3]) < 0.02, X_WC
    R = X_WC[:3, :3].T @ truth.X_WC[:3, :3]
    assert math.degrees(math.acos(np.clip((np.trace(R) - 1) / 2, -1, 1))) < 1.0, R
    WriteRawRecording(
        tmp_path / "raw", rgb=rgb, depth=depth, fps=15.0, intrinsics=intrinsics
    )
    summary = _import(tmp_path / "raw", tmp_path / "demo", table_marker=TABLE_MARKER)
    assert summary["camera_pose_from"].startswith("table marker 3")
    x, y, yaw = LoadDemo(tmp_path / "demo").object_pose
    assert math.hypot(x - POSE[0], y - POSE[1]) < 0.005
    assert abs(math.degrees(yaw) - POSE[2]) < 2.0


def test_a_full_raw_directory_is_refused_before_the_run(tmp_path):
    from fabric_imitation.tools.demo_record import RecordDemo

    (tmp_path / "raw").mkdir()
    (tmp_path / "raw" / "old.png").write_bytes(b"")
    with pytest.raises(InputError, match="raw output directory .* is not empty"):
        RecordDemo(
            scenario=_scenario(),
            scenario_name="box_capture",
            out=tmp_path / "demo",
            export_raw=tmp_path / "raw",
            progress=False,
        )
    assert not (tmp_path / "demo").exists()


def test_a_shadow_on_the_table_is_not_fabric():
    """Dark pixels next to the fabric are fabric in shadow (a fold's inside)
    only above the table: with the depth's heights, a dark patch lying on
    the table beside the cloth is left out, a dark fold above it kept."""
    from fabric_imitation.learning.demo_import import FabricMask

    rgb = np.zeros((60, 90, 3), np.uint8)
    rgb[:] = TABLE
    height = np.zeros((60, 90))
    rgb[20:40, 20:50] = GREEN  # the cloth, 10 cm up
    height[20:40, 20:50] = 0.10
    rgb[20:40, 50:53] = (10, 10, 10)  # a dark fold, 5 cm up
    height[20:40, 50:53] = 0.05
    rgb[20:40, 17:20] = (10, 10, 10)  # its shadow on the table
    mask = FabricMask(rgb, *HSV, height=height)
    assert mask[20:40, 20:53].all()
    assert not mask[:, :20].any()
    # Without depth both dark strips count, as before.
    blind = FabricMask(rgb, *HSV)
    assert blind[22:38, 17:20].all() and blind[20:40, 50:53].all()
