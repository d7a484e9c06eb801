"""Small LeafSystems of the cloth station: fabric mask, ground truth, release."""

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.geometry import GeometryConfigurationVector, GeometryId
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem
from pydrake.systems.sensors import ImageGrey8U, ImageLabel16I


class FabricMask(LeafSystem):
    """Fabric mask from a label image: 255 where the pixel shows the cloth.

    Input ports: ``label_image`` (ImageLabel16I).
    Output ports: ``mask`` (ImageGrey8U).
    """

    def __init__(self, *, width: int, height: int, cloth_label: int):
        super().__init__()
        self._cloth_label = cloth_label
        self._label = self.DeclareAbstractInputPort(
            "label_image", AbstractValue.Make(ImageLabel16I(width, height))
        )
        self.DeclareAbstractOutputPort(
            "mask",
            lambda: AbstractValue.Make(ImageGrey8U(width, height)),
            self._calc_mask,
        )

    def _calc_mask(self, context, output):
        label = self._label.Eval(context).data[:, :, 0]
        mask = output.get_mutable_value()
        mask.mutable_data[:, :, 0] = np.where(label == self._cloth_label, 255, 0)


class ClothGroundTruth(LeafSystem):
    """Simulation-only ground truth of the cloth: vertex positions and the M
    ordered boundary keypoints (learning/state.py), both in world.

    Input ports: ``configuration`` (GeometryConfigurationVector from the plant).
    Output ports: ``positions`` (3N vector, vertex-major x, y, z),
    ``keypoints`` (3M vector, keypoint-major).
    """

    def __init__(
        self,
        *,
        geometry_id: GeometryId,
        num_vertices: int,
        keypoint_vertices: np.ndarray,
    ):
        super().__init__()
        self._id = geometry_id
        self._kp = np.asarray(keypoint_vertices)
        self._config = self.DeclareAbstractInputPort(
            "configuration", AbstractValue.Make(GeometryConfigurationVector())
        )
        self.DeclareVectorOutputPort(
            "positions", 3 * num_vertices, self._calc_positions
        )
        self.DeclareVectorOutputPort(
            "keypoints", 3 * len(self._kp), self._calc_keypoints
        )

    def _positions(self, context) -> np.ndarray:
        return self._config.Eval(context).value(self._id)

    def _calc_positions(self, context, output: BasicVector):
        output.SetFromVector(self._positions(context))

    def _calc_keypoints(self, context, output: BasicVector):
        p = self._positions(context).reshape(-1, 3)
        output.SetFromVector(p[self._kp].ravel())


class ReleaseLatch(LeafSystem):
    """Latches the ``release`` command: once above 0.5 it stays released.

    Opening a grasp changes the plant's constraint parameters, which no system
    event may do; the runners' `diagrams/station.AdvanceStationTo` applies
    it between steps. On hardware the same latch drives the grippers' open command.

    Input ports: ``release`` (1-vector).
    Output ports: ``released`` (1-vector, 0 or 1; from state).
    """

    def __init__(self, *, period: float):
        super().__init__()
        self._release = self.DeclareVectorInputPort("release", 1)
        state = self.DeclareDiscreteState(1)
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)
        self.DeclareForcedDiscreteUpdateEvent(self._update)
        self.DeclareStateOutputPort("released", state)

    def _update(self, context, discrete_state) -> EventStatus:
        released = context.get_discrete_state(0).GetAtIndex(0) > 0.5
        if self._release.HasValue(context) and self._release.Eval(context)[0] > 0.5:
            released = True
        discrete_state.get_mutable_vector(0).SetAtIndex(0, 1.0 if released else 0.0)
        return EventStatus.Succeeded()
