"""Open-loop runs of the cloth station: a fixed action list (scripted demo,
holding still) through the GripperTargetIntegrator, with frame capture,
release, settling, meshcat recording and camera video."""

import dataclasses as dc

import numpy as np
from fabric_imitation.diagrams.station import (
    PEOPLE_CAMERA_SIZE,
    ClothStation,
    StationPorts,
)
from fabric_imitation.learning.state import SIDES
from fabric_imitation.systems.cloth_mesh import TopTriangles
from fabric_imitation.systems.visualization import (
    ClothFrameRecorder,
    VideoRecorder,
)
from pydrake.geometry import Meshcat, Rgba


@dc.dataclass
class Frame:
    """One observation, plus simulation-only ground truth."""

    time: float
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32 metres, inf where nothing
    mask: np.ndarray  # (H, W) uint8, 255 on the cloth
    keypoints_W: np.ndarray  # (M, 3) ground truth
    positions_W: np.ndarray  # (N, 3) ground truth
    grippers_W: np.ndarray  # (2, 3) measured


def CaptureFrame(station: ClothStation, station_context) -> Frame:
    """Reads the station's camera and ground-truth ports."""

    def port(name):
        return station.diagram.GetOutputPort(name).Eval(station_context)

    return Frame(
        time=station_context.get_time(),
        rgb=np.array(port(StationPorts.RGB).data[:, :, :3]),
        depth=np.array(port(StationPorts.DEPTH).data[:, :, 0]),
        mask=np.array(port(StationPorts.MASK).data[:, :, 0]),
        keypoints_W=np.array(port(StationPorts.CLOTH_KEYPOINTS)).reshape(-1, 3),
        positions_W=np.array(port(StationPorts.CLOTH_POSITIONS)).reshape(-1, 3),
        grippers_W=np.stack([port(StationPorts.ee_measured(s)) for s in SIDES]),
    )


VIDEO_FPS = 15.0  # frames per second of the videos for people


def AddClothRecorder(
    builder, station: ClothStation, meshcat: Meshcat
) -> ClothFrameRecorder:
    """Draws the station's cloth into a recording meshcat 16 times a second
    (Drake's own drawing of a deformable body keeps only its last shape)."""
    mesh = station.mesh
    recorder = builder.AddNamedSystem(
        "cloth_recorder",
        ClothFrameRecorder(
            meshcat=meshcat,
            num_vertices=len(mesh.vertices),
            triangles=TopTriangles(mesh.top_layer),
            period=1 / 16,
            rgba=Rgba(*station.scenario.cloth.color, 1.0),
        ),
    )
    builder.Connect(
        station.diagram.GetOutputPort(StationPorts.CLOTH_POSITIONS),
        recorder.GetInputPort("positions"),
    )
    return recorder


def AddVideoRecorder(builder, station: ClothStation) -> VideoRecorder:
    """A VideoRecorder on the station's control camera and, when the station
    has one, its people's camera, at VIDEO_FPS."""
    cam = station.scenario.camera
    cameras = {StationPorts.RGB: (cam.width, cam.height)}
    if station.diagram.HasOutputPort(StationPorts.PEOPLE_RGB):
        cameras[StationPorts.PEOPLE_RGB] = (PEOPLE_CAMERA_SIZE, PEOPLE_CAMERA_SIZE)
    recorder = builder.AddNamedSystem(
        "video", VideoRecorder(cameras=cameras, fps=VIDEO_FPS)
    )
    for port in cameras:
        builder.Connect(
            station.diagram.GetOutputPort(port), recorder.GetInputPort(port)
        )
    return recorder
