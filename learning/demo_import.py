"""`fabric-imitate demo import`: a person's RGB-D recording of the task ->
the demo directory that `demo record` writes, so `imitate --demo DIR` takes
either (the paper's Section V-D: an operator demonstrates with their hands
under a fixed top-down camera; only raw observations are kept; the rigid
object's pose comes from a marker on it).

What a camera driver gives (`WriteRawRecording` writes the same, from
simulation):

- an RGB video (`rgb.mp4`, any codec PyAV reads), frame rate in the file;
- depth: a directory of 16-bit PNGs in millimetres (0: no reading), one per
  video frame in name order, or an `.npz` with `depth` (T, H, W) in metres
  (float) or millimetres (uint16);
- the colour camera's intrinsics in YAML: `width`, `height`, `fx`, `fy`,
  `cx`, `cy` [px] (depth aligned to colour);
- or instead of the three, a ROS 1 / ROS 2 bag with colour, aligned depth and
  camera-info topics (read with the pure-Python `rosbags` package).

Fabric masks come from a mask video or from an HSV colour threshold with
morphological clean-up, the operator's skin removed and the largest
connected component kept. The object's pose comes from an ArUco marker
fixed to it (its offset in the object frame is in the scenario); the camera's
pose from the scenario, or from a second marker lying on the table.
"""

import dataclasses as dc
import functools
import math
from pathlib import Path

import numpy as np
import torch
from fabric_imitation.learning.demo_io import CameraModel
from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.geometry import PinholeCamera

INTRINSICS_KEYS = ("width", "height", "fx", "fy", "cx", "cy")
# Skin in YCrCb (Chai and Ngan 1999): Cr in [133, 173], Cb in [77, 127].
SKIN_CR = (133, 173)
SKIN_CB = (77, 127)
# The object is fixed during a demo: detections may spread this much.
MAX_POSE_SPREAD_M = 0.01
MAX_POSE_SPREAD_DEG = 4.0


@dc.dataclass
class Recording:
    """Raw RGB-D frames as a camera driver gives them."""

    rgb: np.ndarray  # (T, H, W, 3) uint8
    depth: np.ndarray  # (T, H, W) float32 [m], NaN where there is no reading
    fps: float
    intrinsics: dict  # width, height, fx, fy, cx, cy
    source: str

    @property
    def K(self) -> np.ndarray:
        k = self.intrinsics
        return np.array([[k["fx"], 0, k["cx"]], [0, k["fy"], k["cy"]], [0, 0, 1.0]])


# --- reading -----------------------------------------------------------------


def ReadIntrinsics(path: Path) -> dict:
    import yaml

    path = Path(path)
    if not path.is_file():
        raise InputError(f"intrinsics file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError:
        raise InputError(f"intrinsics {path}: not valid YAML") from None
    if not isinstance(data, dict):
        raise InputError(
            f"intrinsics {path}: expected a mapping with {INTRINSICS_KEYS}"
        )
    missing = [k for k in INTRINSICS_KEYS if k not in data]
    if missing:
        raise InputError(f"intrinsics {path}: missing {', '.join(missing)}")
    try:
        out = {k: float(data[k]) for k in INTRINSICS_KEYS}
    except (TypeError, ValueError):
        raise InputError(
            f"intrinsics {path}: {INTRINSICS_KEYS} must be numbers"
        ) from None
    out["width"], out["height"] = int(out["width"]), int(out["height"])
    return out


def ReadVideo(path: Path) -> tuple[np.ndarray, float]:
    """(T, H, W, 3) uint8 RGB frames and the frame rate of a video file."""
    import av

    path = Path(path)
    if not path.is_file():
        raise InputError(f"video not found: {path}")
    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            fps = float(stream.average_rate or stream.guessed_rate or 0)
            frames = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
    except (av.error.FFmpegError, IndexError, ValueError) as e:
        raise InputError(
            f"video {path} cannot be read: {' '.join(str(e).split())[:120]}"
        ) from None
    if not frames:
        raise InputError(f"video {path} has no frames")
    if fps <= 0:
        raise InputError(f"video {path} does not give its frame rate")
    return np.stack(frames), fps


def ReadDepth(path: Path) -> np.ndarray:
    """(T, H, W) float32 depth [m] (NaN: no reading) from a directory of
    16-bit PNGs in millimetres or an .npz with `depth`."""
    import cv2

    path = Path(path)
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() == ".png")
        if not files:
            raise InputError(f"depth directory {path} holds no .png files")
        images = []
        for f in files:
            image = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            if image is None:
                raise InputError(f"depth image {f} cannot be read")
            if image.dtype != np.uint16 or image.ndim != 2:
                raise InputError(
                    f"depth image {f} is not a 16-bit single-channel PNG "
                    f"(millimetres), got {image.dtype} with shape {image.shape}"
                )
            images.append(image)
        if len({im.shape for im in images}) > 1:
            raise InputError(f"depth images in {path} differ in size")
        mm = np.stack(images).astype(np.float32)
    elif path.suffix == ".npz" and path.is_file():
        try:
            with np.load(path) as data:
                raw = data["depth"]
        except (OSError, ValueError, KeyError) as e:
            raise InputError(f"depth file {path} cannot be read: {e}") from None
        if raw.ndim != 3:
            raise InputError(
                f"depth file {path}: depth must be (T, H, W), got {raw.shape}"
            )
        mm = raw.astype(np.float32) if raw.dtype == np.uint16 else raw * 1000.0
    else:
        raise InputError(f"depth not found: {path} (a directory of PNGs or an .npz)")
    depth = mm.astype(np.float32) / 1000.0
    depth[~(depth > 0)] = np.nan
    return depth


def ReadRecording(rgb: Path, depth: Path, intrinsics: Path) -> Recording:
    """Reads and cross-checks a video, its depth and the intrinsics."""
    frames, fps = ReadVideo(rgb)
    d = ReadDepth(depth)
    k = ReadIntrinsics(intrinsics)
    if len(frames) != len(d):
        raise InputError(
            f"video {rgb} has {len(frames)} frames, depth {depth} has {len(d)}"
        )
    if frames.shape[1:3] != d.shape[1:]:
        raise InputError(
            f"video {rgb} frames are {frames.shape[2]} x {frames.shape[1]}, depth "
            f"{depth} images {d.shape[2]} x {d.shape[1]}"
        )
    if (k["width"], k["height"]) != (frames.shape[2], frames.shape[1]):
        raise InputError(
            f"intrinsics {intrinsics} are for {k['width']} x {k['height']} images, "
            f"the video's are {frames.shape[2]} x {frames.shape[1]}"
        )
    return Recording(frames, d, fps, k, source=str(rgb))


def ReadBag(
    path: Path, *, color_topic: str, depth_topic: str, info_topic: str
) -> Recording:
    """A ROS 1 (.bag) or ROS 2 (directory) bag with colour images (rgb8 or
    bgr8), aligned depth (16UC1 in mm or 32FC1 in m) and a CameraInfo topic,
    read with `rosbags` (no ROS installation). Colour and depth are paired
    by nearest header stamp."""
    try:
        from rosbags.highlevel import AnyReader
    except ImportError:
        raise InputError(
            "reading bags needs the `rosbags` package: pip install rosbags"
        ) from None
    path = Path(path)
    if not path.exists():
        raise InputError(f"bag not found: {path}")
    color, depth, info = [], [], None
    try:
        with AnyReader([path]) as reader:
            topics = {c.topic for c in reader.connections}
            missing = [
                t for t in (color_topic, depth_topic, info_topic) if t not in topics
            ]
            if missing:
                raise InputError(
                    f"bag {path} has no topic {', '.join(missing)} (it has: "
                    f"{', '.join(sorted(topics))})"
                )
            wanted = [
                c
                for c in reader.connections
                if c.topic in (color_topic, depth_topic, info_topic)
            ]
            for connection, _, raw in reader.messages(connections=wanted):
                msg = reader.deserialize(raw, connection.msgtype)
                if connection.topic == info_topic:
                    info = info or msg
                    continue
                stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
                image = _ros_image(msg, path)
                (color if connection.topic == color_topic else depth).append(
                    (stamp, image)
                )
    except InputError:
        raise
    except Exception as e:  # noqa: BLE001 (a corrupt bag: one line)
        raise InputError(
            f"bag {path} cannot be read: {' '.join(str(e).split())[:150]}"
        ) from None
    if not color or not depth or info is None:
        raise InputError(f"bag {path}: no messages on one of the named topics")
    color.sort(key=lambda x: x[0])
    depth.sort(key=lambda x: x[0])
    stamps = np.array([s for s, _ in depth])
    pairs = [depth[int(np.abs(stamps - s).argmin())][1] for s, _ in color]
    rgb = np.stack([im for _, im in color])
    d = np.stack(pairs).astype(np.float32)
    d[~(d > 0)] = np.nan
    # ROS 2 names the matrix `k`, ROS 1 `K`.
    K = np.asarray(info.k if hasattr(info, "k") else info.K, float).reshape(3, 3)
    intrinsics = {
        "width": int(info.width),
        "height": int(info.height),
        "fx": K[0, 0],
        "fy": K[1, 1],
        "cx": K[0, 2],
        "cy": K[1, 2],
    }
    times = np.array([s for s, _ in color])
    fps = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 else 1.0
    if rgb.shape[1:3] != d.shape[1:]:
        raise InputError(f"bag {path}: colour and depth images differ in size")
    if (intrinsics["width"], intrinsics["height"]) != (rgb.shape[2], rgb.shape[1]):
        raise InputError(
            f"bag {path}: camera info is for {intrinsics['width']} x "
            f"{intrinsics['height']} images, the colour images are "
            f"{rgb.shape[2]} x {rgb.shape[1]}"
        )
    return Recording(rgb, d, float(fps), intrinsics, source=str(path))


def _ros_image(msg, path) -> np.ndarray:
    h, w = int(msg.height), int(msg.width)
    data = np.frombuffer(bytes(msg.data), np.uint8)
    if msg.encoding in ("rgb8", "bgr8"):
        image = data.reshape(h, int(msg.step))[:, : 3 * w].reshape(h, w, 3)
        return image[:, :, ::-1].copy() if msg.encoding == "bgr8" else image.copy()
    if msg.encoding in ("16UC1", "mono16"):
        return data.view(np.uint16).reshape(h, -1)[:, :w].astype(np.float32) / 1000.0
    if msg.encoding == "32FC1":
        return data.view(np.float32).reshape(h, -1)[:, :w].copy()
    raise InputError(f"bag {path}: image encoding {msg.encoding!r} is not supported")


# --- masks -----------------------------------------------------------------


def SkinMask(rgb: np.ndarray) -> np.ndarray:
    """Pixels of skin colour (YCrCb rule), bool (H, W)."""
    import cv2

    ycrcb = cv2.cvtColor(rgb, cv2.COLOR_RGB2YCrCb)
    cr, cb = ycrcb[:, :, 1], ycrcb[:, :, 2]
    return (
        (cr >= SKIN_CR[0])
        & (cr <= SKIN_CR[1])
        & (cb >= SKIN_CB[0])
        & (cb <= SKIN_CB[1])
    )


# Pixels darker than this (HSV value) within 3 px of the fabric are fabric
# in shadow: a fold's inside, or (in simulation) the cloth's back faces,
# which the renderer draws black; their hue says nothing.
DARK_VALUE = 40
# ... but only where they stand this high [m] above the table, when the
# depth says so: a dark patch on the table next to the fabric (a shadow, a
# marker's black border) is not fabric. Kept, a hanging towel's last frame
# gained the border of the marker plaque beside it, whose depth put its
# grasped corner on the table (simulated hang recording: z 0.001 m, the
# renderer's mask gives 0.156 m).
DARK_MIN_HEIGHT_M = 0.005


def FabricMask(
    rgb: np.ndarray, hsv_low, hsv_high, height: np.ndarray | None = None
) -> np.ndarray:
    """The fabric's mask (H, W) uint8 {0, 1} from an RGB frame: pixels in the
    HSV box [hsv_low, hsv_high] (OpenCV ranges: H 0-179, S and V 0-255) and
    dark pixels next to them (DARK_VALUE; with `height`, the pixels' height
    above the table [m], only those above DARK_MIN_HEIGHT_M), skin removed,
    opened and closed with a 3 x 3 kernel, the largest connected component
    kept."""
    import cv2

    hsv = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV)
    mask = cv2.inRange(hsv, np.array(hsv_low, np.uint8), np.array(hsv_high, np.uint8))
    near = cv2.dilate(mask, np.ones((7, 7), np.uint8)) > 0
    dark = near & (hsv[:, :, 2] < DARK_VALUE)
    if height is not None:
        dark &= np.nan_to_num(height, nan=np.inf) > DARK_MIN_HEIGHT_M
    mask[dark] = 255
    mask[SkinMask(rgb)] = 0
    kernel = np.ones((3, 3), np.uint8)
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, kernel)
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(
        (mask > 0).astype(np.uint8), 8
    )
    if n <= 1:
        return np.zeros(mask.shape, np.uint8)
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return (labels == largest).astype(np.uint8)


# --- markers ---------------------------------------------------------------


@functools.cache
def _Detector(dictionary: str):
    """One ArUco detector per dictionary (sub-pixel corners), made once."""
    import cv2

    aruco = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return cv2.aruco.ArucoDetector(aruco, params)


def _PointsC(u, v, depth, K) -> np.ndarray:
    """Camera-frame points (..., 3) of pixels (u, v) at `depth` (along the
    optical axis)."""
    return np.stack(
        [(u - K[0, 2]) / K[0, 0] * depth, (v - K[1, 2]) / K[1, 1] * depth, depth], -1
    )


def DetectMarker(rgb: np.ndarray, dictionary: str, marker_id: int) -> np.ndarray | None:
    """The 4 corners (4, 2) [px] of marker `marker_id` (OpenCV's order:
    top-left, top-right, bottom-right, bottom-left of the printed marker),
    or None."""
    import cv2

    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    corners, ids, _ = _Detector(dictionary).detectMarkers(gray)
    if ids is None:
        return None
    for c, i in zip(corners, ids.ravel(), strict=True):
        if int(i) == marker_id:
            return c.reshape(4, 2).astype(float)
    return None


def _rays_W(uv: np.ndarray, K: np.ndarray, X_WC: np.ndarray) -> np.ndarray:
    """World directions (N, 3) of pixels uv (N, 2)."""
    p = np.c_[uv, np.ones(len(uv))] @ np.linalg.inv(K).T
    return p @ X_WC[:3, :3].T


def MarkerPoseOnPlane(corners: np.ndarray, K: np.ndarray, X_WC: np.ndarray, z: float):
    """[x, y, yaw] of a marker lying face up at height z [m] (world): its
    corners' rays meet the plane z; yaw is the direction of its top edge
    (corner 0 -> 1)."""
    rays = _rays_W(corners, K, X_WC)
    origin = X_WC[:3, 3]
    s = (z - origin[2]) / rays[:, 2]
    p = origin + s[:, None] * rays
    centre = p.mean(0)
    x_axis = (p[1] - p[0]) + (p[2] - p[3])
    return np.array([centre[0], centre[1], math.atan2(x_axis[1], x_axis[0])])


def CameraPoseFromTableMarker(corners, K, size: float, pose_W, depth=None):
    """X_WC (4, 4) from a marker of side `size` lying face up on the table at
    `pose_W` ([x, y, yaw_deg], its top edge along its x axis).

    With the frame's `depth` [m]: the table's plane is fitted to the depth
    inside the marker (hundreds of points), the corners' rays meet that
    plane, and the rigid transform from those 3-D corners to the marker's
    known corners is the camera's pose (a single small marker seen from
    1 m left PnP's tilt 5 degrees off in the tests). Without depth:
    OpenCV's PnP (IPPE_SQUARE)."""
    import cv2

    h = size / 2
    # The marker frame M: x along the top edge, y towards it, z out of the
    # face; corners in OpenCV's order (top-left, top-right, ...).
    p_M = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]], float)
    c, s = math.cos(math.radians(pose_W[2])), math.sin(math.radians(pose_W[2]))
    X_WM = np.eye(4)
    X_WM[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    X_WM[:3, 3] = [pose_W[0], pose_W[1], 0.0]
    p_W = p_M @ X_WM[:3, :3].T + X_WM[:3, 3]
    rays = np.c_[corners, np.ones(4)] @ np.linalg.inv(K).T  # camera frame, z = 1
    if depth is not None:
        inside = np.zeros(depth.shape, np.uint8)
        cv2.fillPoly(inside, [np.round(corners).astype(np.int32)], 1)
        v, u = np.nonzero((inside > 0) & np.isfinite(depth))
        if len(v) < 20:
            raise InputError("the table marker has too few depth readings")
        pts = _PointsC(u, v, depth[v, u], K)
        centre = pts.mean(0)
        normal = np.linalg.svd(pts - centre)[2][2]
        p_C = rays * ((centre @ normal) / (rays @ normal))[:, None]
        # Kabsch: X_WC maps p_C onto p_W.
        a, b = p_C - p_C.mean(0), p_W - p_W.mean(0)
        U, _, Vt = np.linalg.svd(a.T @ b)
        D = np.diag([1, 1, np.sign(np.linalg.det(Vt.T @ U.T))])
        R = Vt.T @ D @ U.T
        X_WC = np.eye(4)
        X_WC[:3, :3], X_WC[:3, 3] = R, p_W.mean(0) - R @ p_C.mean(0)
        return X_WC
    ok, rvec, tvec = cv2.solvePnP(
        p_M, corners.astype(float), K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE
    )
    if not ok:
        raise InputError("the table marker's pose could not be solved")
    R, _ = cv2.Rodrigues(rvec)
    X_CM = np.eye(4)
    X_CM[:3, :3], X_CM[:3, 3] = R, tvec.ravel()
    return X_WM @ np.linalg.inv(X_CM)


def ObjectPoseFromMarker(marker_pose, offset) -> np.ndarray:
    """[x, y, yaw] of the object frame from the marker's [x, y, yaw] and its
    offset [x, y, z, yaw_deg] in the object frame."""
    yaw = marker_pose[2] - math.radians(offset[3])
    c, s = math.cos(yaw), math.sin(yaw)
    x = marker_pose[0] - (c * offset[0] - s * offset[1])
    y = marker_pose[1] - (s * offset[0] + c * offset[1])
    return np.array([x, y, yaw])


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


# --- the import ------------------------------------------------------------


def WriteRawRecording(
    out: Path, *, rgb: list, depth: list, fps: float, intrinsics: dict
) -> None:
    """Writes what an RGB-D camera driver records (module docstring):
    `rgb.mp4`, `depth/000000.png`... (uint16 mm) and `intrinsics.yaml`,
    atomically (a sibling temporary directory renamed into place)."""
    import os
    import shutil

    import cv2
    import yaml
    from fabric_imitation.learning.demo_io import WriteVideo

    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise InputError(f"raw output directory {out} is not empty")
    tmp = out.with_name(out.name + f".partial-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "depth").mkdir(parents=True)
    try:
        WriteVideo(tmp / "rgb.mp4", rgb, fps)
        for i, d in enumerate(depth):
            mm = np.nan_to_num(np.asarray(d, float) * 1000.0, nan=0.0, posinf=0.0)
            cv2.imwrite(
                str(tmp / "depth" / f"{i:06d}.png"),
                np.clip(np.round(mm), 0, 65535).astype(np.uint16),
            )
        (tmp / "intrinsics.yaml").write_text(
            yaml.safe_dump({k: intrinsics[k] for k in INTRINSICS_KEYS}, sort_keys=False)
        )
        if out.exists():
            out.rmdir()
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


@dc.dataclass
class MarkerSpec:
    dictionary: str
    marker_id: int
    size: float
    offset: list  # [x, y, z, yaw_deg] in the object frame


def ImportDemo(
    *,
    recording: Recording,
    camera,
    task: str,
    scenario_name: str,
    scenario_yaml: str,
    step_seconds: float,
    out: Path,
    marker: MarkerSpec,
    hsv: tuple | None = None,
    masks: np.ndarray | None = None,
    table_marker: dict | None = None,
    max_gap_seconds: float = 1.0,
) -> dict:
    """Builds the demo directory `out` from `recording` alone.

    Args:
        camera: the control camera (a CameraModel: the size, intrinsics and
            pose that f_R was trained with); the recording must be a whole
            multiple of it (intrinsics scaled), and is scaled down to it.
        task, scenario_name, scenario_yaml: what the demo shows and the
            scenario it was recorded for (written into the demo).
        step_seconds: the control period the demo learner expects; frames
            are subsampled to it.
        marker: the object's marker (dictionary, id, side, offset).
        hsv: (low, high) HSV bounds of the fabric's colour, or
        masks: (T, H, W) given fabric masks (a mask video's frames).
        table_marker: {"id", "size", "pose": [x, y, yaw_deg]} of a marker on
            the table that gives the camera's pose (default: `camera`'s).
    Returns the summary written into the demo's manifest.
    """
    import cv2
    from fabric_imitation.learning.demo_io import ExistingDemoRequest, WriteDemo

    if task == "prior":
        raise InputError(
            "the prior scene has no task to demonstrate; use box, hang, ..."
        )
    if ExistingDemoRequest(Path(out)) is not None:
        raise InputError(f"output directory {out} already holds a demo")
    rec, target = recording, camera
    T, H, W = rec.depth.shape
    _CheckIntrinsics(rec, target)
    X_WC, camera_from = _CameraPose(rec, target, marker, table_marker)
    # The recording's camera at its pose, for heights above the table.
    K = rec.K
    camera_W = PinholeCamera(
        CameraModel(
            width=W, height=H, fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], X_WC=X_WC
        )
    )
    masks = _FabricMasks(rec, camera_W, hsv, masks)
    area = masks.reshape(T, -1).mean(1)
    pose, found, spread_m, spread_deg = _ObjectPose(rec, marker, X_WC)
    gaps = _gaps(found)
    long_gap = max_gap_seconds * rec.fps
    # Subsample to the control period, then drop the still frames.
    dt = step_seconds
    stride = max(1, int(round(rec.fps * dt)))
    chosen, trimmed = _TrimToMotion(rec, masks, list(range(0, T - 1, stride)), camera_W)
    # Frames inside a long gap of the marker are reported; the object is
    # fixed, so its pose (the median of the detections) still holds there.
    in_long_gap = [
        k for k in chosen if any(a <= k < b and b - a > long_gap for a, b in gaps)
    ]
    size = (target.width, target.height)
    depth_small = np.stack([_SmallDepth(rec.depth[k], size) for k in chosen])
    mask_small = np.stack([_SmallMask(masks[k], size) for k in chosen])
    empty = [i for i in range(len(mask_small)) if not mask_small[i].any()]
    if empty:
        raise InputError(
            f"{rec.source}: after subsampling, the fabric mask is empty in demo "
            f"frame(s) {empty[:5]}"
        )
    request = {
        "task": task,
        "scenario_name": scenario_name,
        "object_pose": [
            round(float(pose[0]), 6),
            round(float(pose[1]), 6),
            round(math.degrees(float(pose[2])), 4),
        ],
        "source": "import",
    }
    summary = {
        "recording": rec.source,
        "recording_frames": T,
        "recording_fps": round(rec.fps, 3),
        "subsampling": {
            "step_seconds": dt,
            "stride_frames": stride,
            "frames": chosen,
            "final_frame": T - 1,
            "still_frames_dropped": trimmed,
        },
        "camera_pose_from": camera_from,
        "marker": {
            "dictionary": marker.dictionary,
            "id": marker.marker_id,
            "size_m": marker.size,
            "offset": list(marker.offset),
            "frames_detected": int(found.sum()),
            "frames_missing": int((~found).sum()),
            "gaps_frames": [[int(a), int(b)] for a, b in gaps],
            "demo_frames_in_long_gaps": in_long_gap,
            "spread_m": round(spread_m, 4),
            "spread_deg": round(spread_deg, 2),
        },
        "mask_source": "given masks"
        if hsv is None
        else {"hsv_low": list(hsv[0]), "hsv_high": list(hsv[1])},
        "mask_area_fraction": [round(float(a), 4) for a in area],
    }
    WriteDemo(
        Path(out),
        request=request,
        rgb=[
            cv2.resize(rec.rgb[k], size, interpolation=cv2.INTER_AREA)
            for k in [*chosen, T - 1]
        ],
        depth=depth_small.astype(np.float32),
        mask=mask_small,
        final_depth=_SmallDepth(rec.depth[-1], size).astype(np.float32),
        final_mask=_SmallMask(masks[-1], size),
        camera=dc.replace(target, X_WC=X_WC),
        scenario_yaml=scenario_yaml,
        ground_truth=None,
        summary=summary,
        fps=1.0 / dt,
    )
    return {
        **request,
        "num_frames": len(chosen),
        **{k: v for k, v in summary.items() if k != "mask_area_fraction"},
        "mask_area_fraction_min": round(float(area.min()), 4),
        "mask_area_fraction_max": round(float(area.max()), 4),
        "out": str(out),
    }


def _CheckIntrinsics(rec: Recording, target) -> None:
    """The recording must be the control camera scaled up: its intrinsics
    scaled down to the camera's size match the camera's."""
    T, H, W = rec.depth.shape
    sx, sy = target.width / W, target.height / H
    K_scaled = rec.K * np.array([[sx], [sy], [1.0]])
    K_target = np.array(
        [[target.fx, 0, target.cx], [0, target.fy, target.cy], [0, 0, 1]]
    )
    # Pixel-centre convention: scaling maps u -> (u + 0.5) s - 0.5.
    K_scaled[0, 2] = (rec.K[0, 2] + 0.5) * sx - 0.5
    K_scaled[1, 2] = (rec.K[1, 2] + 0.5) * sy - 0.5
    if not np.allclose(K_scaled, K_target, rtol=0.02, atol=1.0):
        raise InputError(
            f"the recording's intrinsics (fx {rec.K[0, 0]:.1f}, fy {rec.K[1, 1]:.1f}, "
            f"cx {rec.K[0, 2]:.1f}, cy {rec.K[1, 2]:.1f} at {W} x {H}) do not match "
            f"the scenario's camera scaled to it (fx {target.fx / sx:.1f}, "
            f"fy {target.fy / sy:.1f} at {target.width} x {target.height}); set "
            "camera in the scenario to the real camera's"
        )


def _CameraPose(rec: Recording, target, marker, table_marker) -> tuple:
    """X_WC (4, 4): the scenario camera's, or from the table marker (the
    middle of its detections); and where it came from."""
    if table_marker is None:
        return np.asarray(target.X_WC, float), "scenario"
    poses = []
    for k in range(len(rec.rgb)):
        c = DetectMarker(rec.rgb[k], marker.dictionary, int(table_marker["id"]))
        if c is not None:
            poses.append(
                CameraPoseFromTableMarker(
                    c,
                    rec.K,
                    table_marker["size"],
                    table_marker["pose"],
                    depth=rec.depth[k],
                )
            )
    if not poses:
        raise InputError(
            f"{rec.source}: table marker {table_marker['id']} found in no frame"
        )
    return (
        poses[len(poses) // 2],
        f"table marker {table_marker['id']} ({len(poses)} frames)",
    )


def _FabricMasks(rec: Recording, camera_W, hsv, masks) -> np.ndarray:
    """(T, H, W) uint8 fabric masks: the given ones, or by colour; refused
    when empty or whole in most frames."""
    T, H, W = rec.depth.shape
    if masks is None:
        if hsv is None:
            raise InputError("give --fabric-hsv LOW HIGH or --mask-video")
        masks = np.stack(
            [
                FabricMask(f, *hsv, height=HeightAboveTable(camera_W, d))
                for f, d in zip(rec.rgb, rec.depth, strict=True)
            ]
        )
    else:
        masks = (np.asarray(masks) > 0).astype(np.uint8)
        if masks.shape != (T, H, W):
            raise InputError(
                f"mask video has {masks.shape[0]} frames of {masks.shape[2]} x "
                f"{masks.shape[1]}; the recording {T} of {W} x {H}"
            )
    area = masks.reshape(T, -1).mean(1)
    if (area == 0).mean() > 0.5:
        raise InputError(
            f"{rec.source}: the fabric mask is empty in {int((area == 0).sum())} of "
            f"{T} frames (check --fabric-hsv)"
        )
    if (area > 0.95).mean() > 0.5:
        raise InputError(
            f"{rec.source}: the fabric mask covers the whole image in "
            f"{int((area > 0.95).sum())} of {T} frames (check --fabric-hsv)"
        )
    return masks


def _ObjectPose(rec: Recording, marker, X_WC) -> tuple:
    """The object's [x, y, yaw] from its marker on the plane of its face:
    per-frame poses' median (circular mean of yaw); the frames it was found
    in, and how far the detections spread [m], [deg] (refused beyond
    MAX_POSE_SPREAD_M / _DEG: a demo's object stays put)."""
    T = len(rec.rgb)
    plane_z = float(marker.offset[2])
    per_frame = np.full((T, 3), np.nan)
    for k in range(T):
        c = DetectMarker(rec.rgb[k], marker.dictionary, marker.marker_id)
        if c is not None:
            per_frame[k] = ObjectPoseFromMarker(
                MarkerPoseOnPlane(c, rec.K, X_WC, plane_z), marker.offset
            )
    found = ~np.isnan(per_frame[:, 0])
    if not found.any():
        raise InputError(
            f"{rec.source}: marker {marker.marker_id} ({marker.dictionary}) "
            "found in no frame"
        )
    pose = np.median(per_frame[found], 0)
    pose[2] = math.atan2(
        np.sin(per_frame[found, 2]).mean(), np.cos(per_frame[found, 2]).mean()
    )
    spread_m = float(np.linalg.norm(per_frame[found, :2] - pose[:2], axis=1).max())
    spread_deg = float(np.degrees(np.abs(_wrap(per_frame[found, 2] - pose[2])).max()))
    if spread_m > MAX_POSE_SPREAD_M or spread_deg > MAX_POSE_SPREAD_DEG:
        raise InputError(
            f"{rec.source}: the object's marker moved during the demo (by "
            f"{100 * spread_m:.1f} cm, {spread_deg:.1f} deg); a demo's object stays put"
        )
    return pose, found, spread_m, spread_deg


def _TrimToMotion(rec: Recording, masks, chosen: list[int], camera_W) -> tuple:
    """The subsampled frames `chosen` without the still ones at either end,
    and what was dropped.

    A person waits before starting and lets the cloth settle after letting
    go: the demo runs from one frame before the operator's hands start
    moving the fabric to the last frame in which they still did (hands:
    skin-coloured pixels above the table next to the fabric); the last
    recorded frame is the demo's final observation. Without hands in view,
    by the fabric's own motion (its mask changing by more than STILL_CHANGE
    per step)."""
    hands = [
        HandsOnFabric(rec.rgb[k], rec.depth[k], masks[k], camera_W) for k in chosen
    ]
    if sum(h is not None for h in hands) >= 2:
        moved = [
            a is not None
            and b is not None
            and float(np.linalg.norm(a - b)) > HANDS_MOVE_M
            for a, b in zip(hands[:-1], hands[1:], strict=True)
        ]
        trim_by = "the hands on the fabric"
    else:
        moved = [
            _mask_change(masks[chosen[i]], masks[chosen[i + 1]]) > STILL_CHANGE
            for i in range(len(chosen) - 1)
        ]
        trim_by = "the fabric's mask"
    if not any(moved):
        return chosen, {"by": trim_by, "leading": 0, "trailing": 0}
    first = moved.index(True)
    last = len(moved) - 1 - moved[::-1].index(True)
    trimmed = {"by": trim_by, "leading": first, "trailing": len(chosen) - (last + 2)}
    return chosen[first : last + 2], trimmed


def _PointSamples(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """`image` at the control camera's `size` (width, height), sampled at the
    small pixels' centres, as a camera of that size renders: no averages
    that would blend the cloth's edge with the table (a hanging towel seen
    from above is a strip 2-3 small pixels wide; mask IoU against the
    renderer's 0.94 sampled, 0.92 averaged)."""
    import cv2

    H, W = image.shape[:2]
    width, height = size
    if W % width == 0 and H % height == 0:
        a, b = H // height, W // width
        return np.ascontiguousarray(image[a // 2 :: a, b // 2 :: b])
    return cv2.resize(image, size, interpolation=cv2.INTER_NEAREST)


def _SmallDepth(depth: np.ndarray, size) -> np.ndarray:
    return _PointSamples(np.nan_to_num(depth, nan=np.inf), size)


def _SmallMask(mask: np.ndarray, size) -> np.ndarray:
    return _PointSamples(mask.astype(np.uint8), size)


# The operator's hands: skin-coloured pixels this high above the table
# [m] (a table's wood can have skin's colour) within HANDS_NEAR_PX of the
# fabric; they act while they move more than HANDS_MOVE_M per control step.
HANDS_MIN_HEIGHT_M = 0.01
HANDS_NEAR_PX = 12
HANDS_MOVE_M = 0.005


def HeightAboveTable(camera: PinholeCamera, depth: np.ndarray) -> np.ndarray:
    """Each pixel's world height [m] (H, W) from a depth image [m] of
    `camera`; -inf where there is no reading (never above the table)."""
    z = camera.height_map(torch.as_tensor(depth, dtype=torch.float32)).numpy()
    return np.where(np.isfinite(depth), z, -np.inf)


def HandsOnFabric(rgb, depth, mask, camera: PinholeCamera) -> np.ndarray | None:
    """Mean world position [m] of the operator's hands in a frame (skin-
    coloured pixels above the table), or None when there are none or none
    of them within HANDS_NEAR_PX of the fabric."""
    import cv2

    hands = SkinMask(rgb) & (HeightAboveTable(camera, depth) > HANDS_MIN_HEIGHT_M)
    hands &= mask == 0
    if hands.sum() < 20:
        return None
    kernel = np.ones((2 * HANDS_NEAR_PX + 1,) * 2, np.uint8)
    if not (hands & (cv2.dilate(mask.astype(np.uint8), kernel) > 0)).any():
        return None
    rays = camera.rays_W.numpy()[hands]
    return (camera.p_WC.numpy() + depth[hands][:, None] * rays).mean(0)


# A subsampled frame counts as still when its fabric mask changed by at most
# this fraction (1 - IoU) from the one before (a settling cloth changes by
# 1-1.7% per 0.2 s, a carried one by 3-23%: simulated box demo).
STILL_CHANGE = 0.02


def _mask_change(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a > 0, b > 0
    union = (a | b).sum()
    return 1.0 - (a & b).sum() / union if union else 0.0


def _gaps(found: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) runs of frames without a detection."""
    gaps, start = [], None
    for k, ok in enumerate(found):
        if not ok and start is None:
            start = k
        if ok and start is not None:
            gaps.append((start, k))
            start = None
    if start is not None:
        gaps.append((start, len(found)))
    return gaps
