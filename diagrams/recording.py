"""Meshcat recordings with the cloth animated, saved as self-contained HTML."""

import os
from pathlib import Path

import numpy as np
from pydrake.geometry import Meshcat

# Drake's own drawing of the deformable cloth (MeshcatVisualizer, prefix
# "scene"); a recording keeps only its last shape, so it is hidden in saved
# recordings and the per-frame meshes of ClothFrameRecorder show the motion.
DRAKE_CLOTH_PATH = "/drake/scene/deformable_geometries"


def MakeRecordingMeshcat() -> Meshcat:
    """A meshcat that is recording from now on."""
    meshcat = Meshcat()
    # Opens framed on the table, from the front right and above.
    meshcat.SetCameraPose(
        camera_in_world=np.array([0.9, -1.0, 0.8]),
        target_in_world=np.array([0.0, 0.0, 0.05]),
    )
    meshcat.StartRecording(
        frames_per_second=32.0, set_visualizations_while_recording=False
    )
    return meshcat


def SaveRecording(meshcat: Meshcat, path: Path | str) -> None:
    """Stops the recording and writes it as one HTML file (atomically)."""
    meshcat.StopRecording()
    meshcat.SetProperty(DRAKE_CLOTH_PATH, "visible", False)
    meshcat.PublishRecording()
    html = meshcat.StaticHtml()
    path = Path(path)
    tmp = path.with_name(path.name + f".partial-{os.getpid()}")
    tmp.write_text(html)
    os.replace(tmp, path)
