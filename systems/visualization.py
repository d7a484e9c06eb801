"""Animates the cloth in a meshcat recording; records camera frames for
videos.

Drake 1.58's meshcat recording keeps only the last shape of a deformable body.
This system adds one triangle mesh per frame under ``/cloth_frames`` and
records each frame's visibility, so the saved HTML replays the cloth's motion.
"""

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.geometry import Meshcat, Rgba
from pydrake.systems.framework import EventStatus, LeafSystem
from pydrake.systems.sensors import ImageDepth32F, ImageRgba8U

CLOTH_FRAMES_PATH = "/cloth_frames"


def FrameName(index: int) -> str:
    return f"{CLOTH_FRAMES_PATH}/frame_{index:05d}"


class ClothFrameRecorder(LeafSystem):
    """Every `period` seconds while meshcat is recording, draws the cloth's top
    surface as frame i and makes it the only visible frame from then on.

    The frame index is derived from the time, so the system has no state.

    Input ports: ``positions`` (3N cloth vertex positions, world).
    `rgba` is the cloth's colour (the scenario's `cloth.color`).
    """

    def __init__(
        self,
        *,
        meshcat: Meshcat,
        num_vertices: int,
        triangles: np.ndarray,
        period: float,
        rgba: Rgba,
    ):
        super().__init__()
        self._meshcat = meshcat
        self._faces = np.ascontiguousarray(np.asarray(triangles, np.int32).T)
        self._period = period
        self._rgba = rgba
        self._positions = self.DeclareVectorInputPort("positions", 3 * num_vertices)
        self.DeclarePeriodicPublishEvent(period, 0.0, self._publish)

    def rgba(self) -> Rgba:
        return self._rgba

    def _publish(self, context) -> EventStatus:
        t = context.get_time()
        i = int(round(t / self._period))
        p = self._positions.Eval(context).reshape(-1, 3).T
        path = FrameName(i)
        self._meshcat.SetTriangleMesh(path, p, self._faces, self._rgba)
        # Hidden before its time, shown from t, hidden when the next one shows.
        if i > 0:
            self._meshcat.SetProperty(path, "visible", False, 0.0)
            self._meshcat.SetProperty(FrameName(i - 1), "visible", False, t)
        self._meshcat.SetProperty(path, "visible", True, t)
        return EventStatus.Succeeded()


class VideoRecorder(LeafSystem):
    """Keeps the colour images on its inputs every 1 / `fps` seconds, for
    videos people watch (nothing reads them back into the diagram).

    Input ports: one ImageRgba8U port per name in `cameras` (name -> (width,
    height)). After a run, `frames[name]` holds (H, W, 3) uint8 RGB arrays.
    One recorder serves one run (the frames live in the system).
    """

    def __init__(self, *, cameras: dict[str, tuple[int, int]], fps: float):
        super().__init__()
        self.fps = fps
        self.frames = {name: [] for name in cameras}
        self._ports = {
            name: self.DeclareAbstractInputPort(
                name, AbstractValue.Make(ImageRgba8U(w, h))
            )
            for name, (w, h) in cameras.items()
        }
        self.DeclarePeriodicPublishEvent(1.0 / fps, 0.0, self._publish)

    def _publish(self, context) -> EventStatus:
        for name, port in self._ports.items():
            self.frames[name].append(np.array(port.Eval(context).data[:, :, :3]))
        return EventStatus.Succeeded()


class RgbdRecorder(LeafSystem):
    """Keeps the colour and depth images on its inputs every 1 / `fps`
    seconds, as an RGB-D camera driver records them (`demo record
    --export-raw`).

    Input ports: ``rgb`` (ImageRgba8U), ``depth`` (ImageDepth32F), both
    width x height. After a run: `rgb` (H, W, 3) uint8 and `depth` (H, W)
    float32 [m] lists and their `times`.
    """

    def __init__(self, *, width: int, height: int, fps: float):
        super().__init__()
        self.fps = fps
        self.rgb, self.depth, self.times = [], [], []
        self._rgb = self.DeclareAbstractInputPort(
            "rgb", AbstractValue.Make(ImageRgba8U(width, height))
        )
        self._depth = self.DeclareAbstractInputPort(
            "depth", AbstractValue.Make(ImageDepth32F(width, height))
        )
        self.DeclarePeriodicPublishEvent(1.0 / fps, 0.0, self._publish)

    def _publish(self, context) -> EventStatus:
        self.rgb.append(np.array(self._rgb.Eval(context).data[:, :, :3]))
        self.depth.append(np.array(self._depth.Eval(context).data[:, :, 0]))
        self.times.append(context.get_time())
        return EventStatus.Succeeded()
