"""Observation-only demonstrations on disk: write atomically, load with checks.

A demo directory holds:

    manifest.json       format, task, scenario name, object pose, frame times,
                        camera, sha256 of every file, success of the recording
    rgb.mp4             the camera's colour video (lossy, for people)
    observations.npz    depth (T, H, W) float32 metres and mask (T, H, W) uint8,
                        frames 0..T-1 up to the release; final_depth/final_mask
                        after release and settling (lossless)
    camera.json         intrinsics and X_WC (camera pose in world, 4x4)
    scenario.yaml       the scenario the demo was recorded in
    ground_truth.npz    simulation only: keypoints (T, M, 3) and the final cloth
                        vertices in world; for evaluation, never for imitation

There are no actions in a demo.
"""

import dataclasses as dc
import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np
from fabric_imitation.learning.errors import InputError

DEMO_FORMAT = "fabric-imitation-demo"
DEMO_VERSION = 1


@dc.dataclass
class CameraModel:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    X_WC: np.ndarray  # (4, 4) camera pose in world

    @classmethod
    def FromIntrinsics(cls, intrinsics, X_WC: np.ndarray) -> "CameraModel":
        """From a Drake CameraInfo (width(), focal_x(), center_x(), ...) and
        the camera's (4, 4) pose in world."""
        k = intrinsics
        return cls(
            width=k.width(),
            height=k.height(),
            fx=k.focal_x(),
            fy=k.focal_y(),
            cx=k.center_x(),
            cy=k.center_y(),
            X_WC=np.asarray(X_WC),
        )

    def to_json(self) -> dict:
        d = dc.asdict(self)
        d["X_WC"] = np.asarray(self.X_WC).tolist()
        return d

    @classmethod
    def from_json(cls, d: dict) -> "CameraModel":
        try:
            return cls(
                width=int(d["width"]),
                height=int(d["height"]),
                fx=float(d["fx"]),
                fy=float(d["fy"]),
                cx=float(d["cx"]),
                cy=float(d["cy"]),
                X_WC=np.array(d["X_WC"], dtype=float),
            )
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(
                f"camera description is incomplete or malformed: {e}"
            ) from None

    def same_as(self, other: "CameraModel", tol: float = 1e-6) -> bool:
        return (
            (self.width, self.height) == (other.width, other.height)
            and np.allclose(
                [self.fx, self.fy, self.cx, self.cy],
                [other.fx, other.fy, other.cx, other.cy],
                atol=tol,
            )
            and np.allclose(self.X_WC, other.X_WC, atol=1e-4)
        )


@dc.dataclass
class Demo:
    """A loaded demonstration."""

    path: Path
    manifest: dict
    camera: CameraModel
    depth: np.ndarray  # (T, H, W) float32
    mask: np.ndarray  # (T, H, W) uint8
    final_depth: np.ndarray  # (H, W)
    final_mask: np.ndarray  # (H, W)
    object_pose: np.ndarray  # [x, y, yaw_rad]
    scenario_yaml: str

    @property
    def num_frames(self) -> int:
        return len(self.mask)

    @property
    def task(self) -> str:
        return self.manifest["task"]


def FileSha256(path: Path) -> str:
    """sha256 hex digest of a file, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


VIDEO_MIN_SIZE = 480  # [px] videos for people are upscaled to at least this


def WriteVideo(
    path: Path, rgb_frames: list[np.ndarray], fps: float, *, min_size: int = 0
) -> None:
    """Writes (H, W, 3) uint8 RGB frames as H.264 mp4 (yuv420p: what browsers
    play), through a temporary file. With `min_size`, frames smaller than it
    are upscaled by the smallest integer factor that reaches it (nearest
    neighbour: the camera's pixels stay visible as pixels)."""
    import av
    import cv2

    path = Path(path)
    h, w = rgb_frames[0].shape[:2]
    k = max(1, -(-min_size // min(h, w))) if min_size else 1
    # yuv420p needs even sizes
    W, H = (w * k + 1) // 2 * 2, (h * k + 1) // 2 * 2
    tmp = path.with_name(path.stem + f".partial-{os.getpid()}" + path.suffix)
    try:
        with av.open(str(tmp), mode="w", format="mp4") as container:
            stream = container.add_stream("libx264", rate=int(round(fps)))
            stream.width, stream.height = W, H
            stream.pix_fmt = "yuv420p"
            stream.options = {"crf": "20", "preset": "veryfast"}
            for frame in rgb_frames:
                image = np.ascontiguousarray(frame[:, :, :3])
                if (w, h) != (W, H):
                    image = cv2.resize(image, (W, H), interpolation=cv2.INTER_NEAREST)
                for packet in stream.encode(av.VideoFrame.from_ndarray(image)):
                    container.mux(packet)
            for packet in stream.encode():
                container.mux(packet)
    except Exception:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, path)


def WriteDemo(
    out: Path,
    *,
    request: dict,
    rgb: list[np.ndarray],
    depth: np.ndarray,
    mask: np.ndarray,
    final_depth: np.ndarray,
    final_mask: np.ndarray,
    camera: CameraModel,
    scenario_yaml: str,
    ground_truth: dict[str, np.ndarray] | None,
    summary: dict,
    fps: float,
) -> None:
    """Writes a demo directory atomically: everything goes into a sibling
    temporary directory that is renamed into place at the end.

    `request` (task, scenario name, object pose) identifies the demo; an
    existing directory must be empty or hold the same request.
    """
    out = Path(out)
    tmp = out.with_name(out.name + f".partial-{os.getpid()}")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    try:
        WriteVideo(tmp / "rgb.mp4", rgb, fps)
        np.savez_compressed(
            tmp / "observations.npz",
            depth=depth.astype(np.float32),
            mask=mask.astype(np.uint8),
            final_depth=final_depth.astype(np.float32),
            final_mask=final_mask.astype(np.uint8),
        )
        (tmp / "camera.json").write_text(json.dumps(camera.to_json(), indent=1))
        (tmp / "scenario.yaml").write_text(scenario_yaml)
        if ground_truth is not None:  # simulation only
            np.savez_compressed(tmp / "ground_truth.npz", **ground_truth)
        files = {p.name: FileSha256(p) for p in sorted(tmp.iterdir())}
        manifest = {
            "format": DEMO_FORMAT,
            "version": DEMO_VERSION,
            **request,
            "num_frames": int(len(mask)),
            "files": files,
            **summary,
        }
        (tmp / "manifest.json").write_text(json.dumps(manifest, indent=1))
        if out.exists():
            out.rmdir()  # empty (checked by the caller); raises if not
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def ExistingDemoRequest(out: Path) -> dict | None:
    """The request of a demo already in `out`; None if `out` is absent or an
    empty directory. Raises InputError if `out` holds anything else."""
    out = Path(out)
    if not out.exists():
        return None
    if not out.is_dir():
        raise InputError(f"output path {out} exists and is not a directory")
    if not any(out.iterdir()):
        return None
    manifest = out / "manifest.json"
    if not manifest.is_file():
        raise InputError(f"output directory {out} is not empty and holds no demo")
    try:
        return json.loads(manifest.read_text())
    except json.JSONDecodeError:
        raise InputError(
            f"output directory {out} holds a corrupt manifest.json"
        ) from None


def LoadDemo(path: Path | str, *, verify: bool = True) -> Demo:
    """Loads and checks a demo directory.

    Raises:
        InputError: missing directory or file, corrupt or truncated file,
            checksum mismatch, inconsistent shapes, a frame with an empty mask.
    """
    path = Path(path)
    if not path.is_dir():
        raise InputError(f"demo directory not found: {path}")
    manifest_path = path / "manifest.json"
    if not manifest_path.is_file():
        raise InputError(f"demo {path} has no manifest.json")
    try:
        manifest = json.loads(manifest_path.read_text())
    except json.JSONDecodeError:
        raise InputError(f"demo {path}: manifest.json is corrupt") from None
    if manifest.get("format") != DEMO_FORMAT:
        raise InputError(f"demo {path}: not a {DEMO_FORMAT} directory")
    for name, digest in manifest.get("files", {}).items():
        f = path / name
        if not f.is_file():
            raise InputError(f"demo {path}: file {name} is missing")
        if verify and FileSha256(f) != digest:
            raise InputError(
                f"demo {path}: file {name} is truncated or changed (checksum mismatch)"
            )
    try:
        camera = CameraModel.from_json(json.loads((path / "camera.json").read_text()))
        with np.load(path / "observations.npz") as obs:
            depth, mask = obs["depth"], obs["mask"]
            final_depth, final_mask = obs["final_depth"], obs["final_mask"]
        scenario_yaml = (path / "scenario.yaml").read_text()
    except (OSError, ValueError, KeyError, json.JSONDecodeError) as e:
        raise InputError(f"demo {path}: cannot read observations: {e}") from None
    if depth.shape != mask.shape or depth.ndim != 3:
        raise InputError(
            f"demo {path}: depth {depth.shape} and mask {mask.shape} shapes disagree"
        )
    if depth.shape[1:] != (camera.height, camera.width):
        raise InputError(
            f"demo {path}: frames are {depth.shape[1:]}, camera says "
            f"{(camera.height, camera.width)}"
        )
    empty = [i for i in range(len(mask)) if not mask[i].any()]
    if empty:
        raise InputError(
            f"demo {path}: the fabric mask is empty in frame(s) {empty[:5]}"
        )
    pose = manifest["object_pose"]
    return Demo(
        path=path,
        manifest=manifest,
        camera=camera,
        depth=depth,
        mask=mask,
        final_depth=final_depth,
        final_mask=final_mask,
        object_pose=np.array([pose[0], pose[1], np.radians(pose[2])]),
        scenario_yaml=scenario_yaml,
    )
