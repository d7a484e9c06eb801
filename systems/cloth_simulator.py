"""A triangle-mesh cloth simulated by `newton`'s VBD solver, as a Drake
LeafSystem co-simulated with the station's MultibodyPlant.

The cloth is a sheet of nx x ny particles (the top face of the station's slab
mesh). Its state (particle positions and velocities, the grippers' positions
at the last update, whether the grasps are open) lives in the Context as
discrete state, advanced by a periodic discrete update at the plant's time
step with internal substeps, so Simulator resets, context copies and
recordings work as they do for the plant. The newton model and solver are
scratch space: every update copies the Context's state in and the result out.

Coupling is one-way: the grippers (read from the plant) move the grasped
corner patches kinematically and the table and the task object push the
cloth, but the cloth exerts no force on anything in the plant.

Bending (`VbdConfig.bending_model`): "quadratic", the isometric bending
energy of Bergou et al. 2006 ("A quadratic bending model for inextensible
surfaces"), computed here as an external force once per substep (its
Hessian is constant; stable for the stiffness a cloth has, checked when the
system is built), or "dihedral", newton's own dihedral-angle bending inside
the VBD iterations (about twice the cost of the whole step: it evaluates the
angle's derivatives for all four stencil vertices to use one).

The outputs give the cloth as the FEM slab's vertices (top layer = the
sheet, bottom layer = the sheet moved one thickness against its normals), so
everything that reads `cloth.positions` / `cloth.keypoints` works with
either engine, and a `GeometryConfigurationVector` that places the slab
geometry this system registered in SceneGraph, so the camera's label and
depth images and meshcat see the cloth.

Input ports: ``left.gripper_position``, ``right.gripper_position`` (3, world),
``release`` (1, > 0.5 opens both grasps; latched in state).
Output ports: ``positions`` (3 x slab vertices), ``keypoints`` (3M),
``geometry_configuration`` (GeometryConfigurationVector).
"""

import dataclasses as dc
import glob
import logging
import os

import numpy as np
from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.state import SIDES
from fabric_imitation.scenarios.schema import (
    CONTACT_ELEMENTS,
    DEFAULT_BENDING_DAMPING,
    VbdConfig,
)
from pydrake.common.value import AbstractValue
from pydrake.geometry import GeometryConfigurationVector, GeometryId
from pydrake.math import RigidTransform
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem

log = logging.getLogger(__name__)
_WARP_READY = False


class ClothDivergedError(RuntimeError):
    """The cloth simulation produced non-finite or runaway vertices."""


COLLIDER_SHAPES = ("box", "cylinder")


@dc.dataclass(frozen=True)
class StaticCollider:
    """A static box or cylinder the cloth collides with: pose of its centre,
    full size [m] (a cylinder: diameter, diameter, length along its frame's
    z axis), Coulomb friction, and which of the cloth's elements touch it
    where `VbdConfig.surface_contact` is on (CONTACT_ELEMENTS: "surface"
    particles, edges and faces; "edges" particles and edges; "particles")."""

    X_WB: RigidTransform
    size: tuple[float, float, float]
    friction: float
    contact: str = "surface"
    shape: str = "box"

    def __post_init__(self):
        if self.contact not in CONTACT_ELEMENTS:
            raise ValueError(
                f"unknown contact {self.contact!r} (one of: "
                f"{', '.join(CONTACT_ELEMENTS)})"
            )
        if self.shape not in COLLIDER_SHAPES:
            raise ValueError(
                f"unknown collider shape {self.shape!r} (one of: "
                f"{', '.join(COLLIDER_SHAPES)})"
            )


# Held or free, no vertex of a sane cloth strays this far [m] from the world
# origin.
RUNAWAY_DISTANCE = 5.0


def ResolvedBendingDamping(settings: VbdConfig) -> float:
    """The settings' bending damping, or its bending model's default."""
    if settings.bending_damping is not None:
        return settings.bending_damping
    return DEFAULT_BENDING_DAMPING[settings.bending_model]


def _init_warp():
    """Imports and initialises warp quietly; says in one log line when
    newton's kernels are not in the kernel cache yet (they compile now)."""
    global _WARP_READY
    import warp as wp

    if not _WARP_READY:
        wp.config.quiet = True
        wp.config.log_level = wp.LOG_WARNING
        # The cloth runs forward only (no gradients): without the adjoint
        # kernels newton's modules compile in half the time (the box scene's
        # first step with an empty kernel cache: 50 s against 104 s on 2
        # cores) and the forward code, and so every vertex position, is the
        # same bit for bit (checked on the scripted box cover).
        wp.config.enable_backward = False
        # Warp's native library prints a CUDA-driver warning on machines
        # without a GPU; the CPU is what the cloth runs on, so keep it quiet.
        saved = os.dup(2)
        try:
            with open(os.devnull, "w") as null:
                os.dup2(null.fileno(), 2)
                wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        cache = wp.config.kernel_cache_dir or os.path.expanduser("~/.cache/warp")
        if not glob.glob(os.path.join(cache, "wp_newton*vbd*particle_vbd_kernels*")):
            log.warning(
                "newton VBD cloth: compiling its CPU kernels (once per machine, "
                "about 1 minute on 2 cores; cached in %s for later runs)",
                cache,
            )
        _WARP_READY = True
    return wp


def BendingStencils(triangles: np.ndarray) -> np.ndarray:
    """(E, 4) particle indices (o0, o1, a, b) of every interior edge a-b of
    the triangle mesh, o0 and o1 the vertices opposite it in its two
    triangles."""
    opposite = {}
    stencils = []
    for tri in np.asarray(triangles):
        for k in range(3):
            a, b, o = int(tri[k]), int(tri[(k + 1) % 3]), int(tri[(k + 2) % 3])
            key = (min(a, b), max(a, b))
            if key in opposite:
                stencils.append((opposite[key], o, *key))
            else:
                opposite[key] = o
    return np.array(stencils, dtype=np.int32).reshape(-1, 4)


def QuadraticBendingWeights(
    rest_positions: np.ndarray, stencils: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Weights w (E, 4) and rest lengths (E,) of the quadratic bending
    energy E = 1/2 k L |sum_i w_i x_i|^2 of each stencil (o0, o1, a, b) of a
    flat rest mesh: w is the four rest points' affine dependency (sum w = 0,
    sum w x = 0, so rigid motions and in-plane deformations of the rest shape
    cost nothing) scaled so that |sum w x| = 2 sin(theta / 2) when the
    hinge bends by theta. For small angles the energy is then newton's
    dihedral 1/2 k L theta^2."""
    x = np.asarray(rest_positions, float)
    o0, o1, a, b = (x[stencils[:, k]] for k in range(4))
    edge = b - a
    length = np.linalg.norm(edge, axis=1)
    along = edge / length[:, None]
    a0 = np.einsum("ij,ij->i", o0 - a, along)
    a1 = np.einsum("ij,ij->i", o1 - a, along)
    w0 = 1.0 / np.linalg.norm(o0 - a - a0[:, None] * along, axis=1)
    w1 = 1.0 / np.linalg.norm(o1 - a - a1[:, None] * along, axis=1)
    wb = -(a0 * w0 + a1 * w1) / length
    wa = -(w0 + w1 + wb)
    return np.stack([w0, w1, wa, wb], axis=1), length


def ExplicitBendingStability(
    stencils: np.ndarray,
    weights: np.ndarray,
    lengths: np.ndarray,
    masses: np.ndarray,
    *,
    stiffness: float,
    damping: float,
    substep: float,
) -> float:
    """How close the explicit quadratic bending is to its stability limit at
    this substep [s]: h (sqrt(lambda_K) + lambda_C), with lambda the
    Gershgorin bounds of M^-1 K and M^-1 C over the free particles (the
    symplectic Euler step of an undamped oscillator is stable below
    h sqrt(lambda) = 2, an explicit damper below h lambda = 2); <= 1 keeps a
    margin of two."""
    row = np.zeros(len(masses))
    spread = np.abs(weights).sum(axis=1) * lengths
    for k in range(4):
        np.add.at(row, stencils[:, k], np.abs(weights[:, k]) * spread)
    free = masses > 0
    bound = float((row[free] / masses[free]).max(initial=0.0))
    return substep * (np.sqrt(stiffness * bound) + damping * bound)


def _lumped_masses(positions, triangles, areal_density) -> np.ndarray:
    p = np.asarray(positions, float)
    t = np.asarray(triangles)
    area = 0.5 * np.linalg.norm(
        np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]]), axis=1
    )
    m = np.zeros(len(p))
    for k in range(3):
        np.add.at(m, t[:, k], areal_density * area / 3)
    return m


_HOLD_KERNEL = None
_BEND_KERNEL = None


def _hold_kernel(wp):
    """The kernel that moves held particles with their grippers (defined
    once per process, after warp is imported)."""
    global _HOLD_KERNEL
    if _HOLD_KERNEL is None:
        _HOLD_KERNEL = _define_hold_kernel(wp)
    return _HOLD_KERNEL


def _bend_kernel(wp):
    """The kernel that adds the quadratic bending forces (defined once per
    process, after warp is imported)."""
    global _BEND_KERNEL
    if _BEND_KERNEL is None:

        @wp.kernel
        def quadratic_bending(
            stencils: wp.array2d[wp.int32],
            weights: wp.array2d[float],
            stiffness: wp.array[float],
            damping: wp.array[float],
            q: wp.array[wp.vec3],
            qd: wp.array[wp.vec3],
            f: wp.array[wp.vec3],
        ):
            e = wp.tid()
            bend = wp.vec3(0.0)
            rate = wp.vec3(0.0)
            for k in range(4):
                p = stencils[e, k]
                bend += weights[e, k] * q[p]
                rate += weights[e, k] * qd[p]
            g = -(stiffness[e] * bend + damping[e] * rate)
            for k in range(4):
                wp.atomic_add(f, stencils[e, k], weights[e, k] * g)

        _BEND_KERNEL = quadratic_bending
    return _BEND_KERNEL


def _define_hold_kernel(wp):

    @wp.func
    def turned(offset: wp.vec3, rest: wp.vec3, edge: wp.vec3):
        """`offset` turned about z by the angle from `rest` to `edge` (seen
        from above)."""
        a = wp.atan2(
            rest[0] * edge[1] - rest[1] * edge[0], rest[0] * edge[0] + rest[1] * edge[1]
        )
        c = wp.cos(a)
        s = wp.sin(a)
        return wp.vec3(
            c * offset[0] - s * offset[1], s * offset[0] + c * offset[1], offset[2]
        )

    @wp.func
    def grasped_edge(start: wp.array[wp.vec3], end: wp.array[wp.vec3], alpha: float):
        return start[1] - start[0] + alpha * (end[1] - end[0] - start[1] + start[0])

    @wp.func
    def outside_colliders(
        x: wp.vec3,
        box_p: wp.array[wp.vec3],
        box_R: wp.array[wp.mat33],
        box_half: wp.array[wp.vec3],
        is_round: wp.array[wp.int32],
    ):
        """`x`, or where it lies inside a collider, the nearest point of that
        collider's surface: a box's along the axis of least depth, a
        cylinder's (`is_round` 1; axis z, radius half[0]) radially or along its
        axis, whichever is shallower."""
        for b in range(box_p.shape[0]):
            local = wp.transpose(box_R[b]) * (x - box_p[b])
            h = box_half[b]
            out = local
            if is_round[b] != 0:
                r = wp.sqrt(local[0] * local[0] + local[1] * local[1])
                radial = h[0] - r
                axial = h[2] - wp.abs(local[2])
                if radial > 0.0 and axial > 0.0:
                    if radial < axial and r > 1.0e-9:
                        out[0] = local[0] * h[0] / r
                        out[1] = local[1] * h[0] / r
                    else:
                        out[2] = wp.sign(local[2]) * h[2]
                    x = box_p[b] + box_R[b] * out
            else:
                depth = wp.vec3(
                    h[0] - wp.abs(local[0]),
                    h[1] - wp.abs(local[1]),
                    h[2] - wp.abs(local[2]),
                )
                if depth[0] > 0.0 and depth[1] > 0.0 and depth[2] > 0.0:
                    k = 0
                    if depth[1] < depth[k]:
                        k = 1
                    if depth[2] < depth[k]:
                        k = 2
                    out[k] = wp.sign(local[k]) * h[k]
                    x = box_p[b] + box_R[b] * out
        return x

    @wp.kernel
    def hold_grasped(
        indices: wp.array[wp.int32],
        side: wp.array[wp.int32],
        offsets: wp.array[wp.vec3],
        start: wp.array[wp.vec3],
        end: wp.array[wp.vec3],
        rest_edge: wp.array[wp.vec3],
        holding: wp.array[wp.int32],
        alpha: float,
        step: float,
        inv_dt: float,
        turn: int,
        box_p: wp.array[wp.vec3],
        box_R: wp.array[wp.mat33],
        box_half: wp.array[wp.vec3],
        is_round: wp.array[wp.int32],
        q: wp.array[wp.vec3],
        qd: wp.array[wp.vec3],
    ):
        i = wp.tid()
        if holding[0] == 0:
            return
        s = side[i]
        p = indices[i]
        offset = offsets[i]
        velocity = (end[s] - start[s]) * inv_dt
        if turn != 0:
            # The patch turns about z with the grasped edge (left to right
            # gripper) from its direction at rest.
            offset = turned(offsets[i], rest_edge[0], grasped_edge(start, end, alpha))
            before = turned(
                offsets[i], rest_edge[0], grasped_edge(start, end, alpha - step)
            )
            velocity = velocity + (offset - before) * (inv_dt / step)
        # A held particle carried into a collider (the patch reaches past
        # the fingers, which keep clear of the object) lies on its surface,
        # as the cloth around a pinch folds over an edge.
        q[p] = outside_colliders(
            start[s] + alpha * (end[s] - start[s]) + offset,
            box_p,
            box_R,
            box_half,
            is_round,
        )
        qd[p] = velocity

    return hold_grasped


class ClothSimulator(LeafSystem):
    """Newton VBD cloth (see module docstring).

    Args:
        sheet_W: (N, 3) rest positions of the sheet's particles in world.
        triangles: (T, 3) counter-clockwise (seen from above) particle indices.
        slab_top: (N,) slab vertex index of each particle (the top layer).
        slab_bottom: (N,) slab vertex index under each particle.
        thickness: slab thickness [m] (the bottom layer's offset).
        keypoint_vertices: (M,) slab vertex indices of the keypoints.
        grasped: side -> particle indices held by that gripper.
        grippers_W0: side -> the gripper's world position at rest.
        colliders: static boxes and cylinders (table, task object's parts).
        settings: the scenario's `cloth.vbd`.
        friction: the cloth's Coulomb friction with every collider.
        time_step: period of the discrete update [s].
        geometry_id: the slab geometry registered in SceneGraph (or None).
    """

    def __init__(
        self,
        *,
        sheet_W: np.ndarray,
        triangles: np.ndarray,
        slab_top: np.ndarray,
        slab_bottom: np.ndarray,
        thickness: float,
        keypoint_vertices: np.ndarray,
        grasped: dict,
        grippers_W0: dict,
        colliders: list[StaticCollider],
        settings: VbdConfig,
        friction: float,
        time_step: float,
        geometry_id: GeometryId | None = None,
    ):
        super().__init__()
        if settings.substeps % 2:
            raise ValueError("vbd substeps must be even (graph capture swaps states)")
        self._sheet0 = np.asarray(sheet_W, dtype=float)
        self._n = len(self._sheet0)
        self._tris = np.asarray(triangles, dtype=np.int32)
        self._top = np.asarray(slab_top)
        self._bottom = np.asarray(slab_bottom)
        self._num_slab = 2 * self._n
        self._thickness = thickness
        self._kp = np.asarray(keypoint_vertices)
        sheet_of_slab = {v: i for i, v in enumerate(self._top)}
        if not all(v in sheet_of_slab for v in self._kp):
            raise ValueError("keypoint vertices must lie on the slab's top layer")
        self._kp_sheet = np.array([sheet_of_slab[v] for v in self._kp])
        self._grasped = {s: np.asarray(grasped[s], dtype=np.int32) for s in SIDES}
        self._dt = time_step
        self._bending = None
        if settings.bending_model == "quadratic":
            self._bending = self._quadratic_bending(settings, time_step)
        self._settings = settings
        self._friction = friction
        self._colliders = list(colliders)
        self._geometry_id = geometry_id
        self._engine = None  # built on first update (kernels compile then)

        self._grippers_W0 = {s: np.asarray(grippers_W0[s], float) for s in SIDES}
        g0 = np.concatenate([grippers_W0[s] for s in SIDES])
        x0 = np.concatenate([self._sheet0.ravel(), np.zeros(3 * self._n)])
        self._cloth_state = self.DeclareDiscreteState(BasicVector(x0))
        self._gripper_state = self.DeclareDiscreteState(BasicVector(g0))
        self._released_state = self.DeclareDiscreteState(1)
        self._grippers = {
            s: self.DeclareVectorInputPort(f"{s}.gripper_position", 3) for s in SIDES
        }
        self._release = self.DeclareVectorInputPort("release", 1)
        self.DeclarePeriodicDiscreteUpdateEvent(time_step, 0.0, self._update)
        self._positions = self.DeclareVectorOutputPort(
            "positions",
            3 * self._num_slab,
            self._calc_positions,
            {self.discrete_state_ticket(self._cloth_state)},
        )
        self.DeclareVectorOutputPort(
            "keypoints",
            3 * len(self._kp),
            self._calc_keypoints,
            {self.discrete_state_ticket(self._cloth_state)},
        )
        self.DeclareAbstractOutputPort(
            "geometry_configuration",
            lambda: AbstractValue.Make(GeometryConfigurationVector()),
            self._calc_configuration,
            {self.discrete_state_ticket(self._cloth_state)},
        )

    def _quadratic_bending(self, settings: VbdConfig, time_step: float):
        """Stencils, weights and per-stencil stiffness and damping [N/m, N s/m]
        of the quadratic bending; a bending too stiff for the explicit step
        is an InputError."""
        stencils = BendingStencils(self._tris)
        weights, lengths = QuadraticBendingWeights(self._sheet0, stencils)
        masses = _lumped_masses(self._sheet0, self._tris, settings.areal_density)
        for s in SIDES:
            masses[self._grasped[s]] = 0.0  # held: moved by the grippers
        h = time_step / settings.substeps
        margin = ExplicitBendingStability(
            stencils,
            weights,
            lengths,
            masses,
            stiffness=settings.bending_stiffness,
            damping=ResolvedBendingDamping(settings),
            substep=h,
        )
        if margin > 1.0:
            raise InputError(
                f"cloth.vbd bending_stiffness {settings.bending_stiffness:g} / "
                f"bending_damping {ResolvedBendingDamping(settings):g} are too "
                "stiff for "
                f"the explicit quadratic bending at {1e3 * h:g} ms substeps "
                f"({margin:.2f} of the stable limit, 1 allowed): use more "
                "cloth.vbd.substeps or bending_model: dihedral"
            )
        return (
            stencils,
            weights,
            settings.bending_stiffness * lengths,
            ResolvedBendingDamping(settings) * lengths,
        )

    # ----- outputs -------------------------------------------------------
    def _sheet(self, context) -> np.ndarray:
        x = context.get_discrete_state(self._cloth_state).value()
        return x[: 3 * self._n].reshape(-1, 3)

    def SlabPositions(self, sheet: np.ndarray) -> np.ndarray:
        """(2N, 3) slab vertices: the sheet on top, one thickness below it
        along the area-weighted vertex normals."""
        a, b, c = (sheet[self._tris[:, k]] for k in range(3))
        face = np.cross(b - a, c - a)
        normals = np.zeros_like(sheet)
        for k in range(3):
            np.add.at(normals, self._tris[:, k], face)
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        degenerate = length[:, 0] <= 1e-12  # collapsed triangles: point up
        normals[degenerate], length[degenerate] = [0.0, 0.0, 1.0], 1.0
        normals /= length
        slab = np.empty((self._num_slab, 3))
        slab[self._top] = sheet
        slab[self._bottom] = sheet - self._thickness * normals
        return slab

    def _calc_positions(self, context, output: BasicVector):
        output.SetFromVector(self.SlabPositions(self._sheet(context)).ravel())

    def _calc_keypoints(self, context, output: BasicVector):
        # Keypoints are top-face vertices: particles themselves.
        output.SetFromVector(self._sheet(context)[self._kp_sheet].ravel())

    def _calc_configuration(self, context, output):
        config = GeometryConfigurationVector()
        if self._geometry_id is not None:
            # The cached `positions` output: the normals are computed once.
            config.set_value(self._geometry_id, self._positions.Eval(context))
        output.set_value(config)

    # ----- dynamics ------------------------------------------------------
    def _update(self, context, discrete_state) -> EventStatus:
        engine = self._engine or self._build()
        x = context.get_discrete_state(self._cloth_state).value()
        g_start = context.get_discrete_state(self._gripper_state).value()
        released = context.get_discrete_state(self._released_state).value()[0] > 0.5
        if self._release.HasValue(context) and self._release.Eval(context)[0] > 0.5:
            released = True
        g_end = np.concatenate(
            [
                self._grippers[s].Eval(context)
                if self._grippers[s].HasValue(context)
                else g_start[3 * i : 3 * i + 3]
                for i, s in enumerate(SIDES)
            ]
        )
        q_new, qd_new = engine.step(x, g_start, g_end, held=not released)
        finite = bool(np.isfinite(q_new).all())
        if not finite or np.abs(q_new).max() > RUNAWAY_DISTANCE:
            raise ClothDivergedError(
                f"vbd cloth diverged at t = {context.get_time():.3f} s "
                "(non-finite or runaway vertices)"
            )
        discrete_state.get_mutable_vector(self._cloth_state).SetFromVector(
            np.concatenate([q_new.ravel(), qd_new.ravel()])
        )
        discrete_state.get_mutable_vector(self._gripper_state).SetFromVector(g_end)
        discrete_state.get_mutable_vector(self._released_state).SetAtIndex(
            0, 1.0 if released else 0.0
        )
        return EventStatus.Succeeded()

    def _build(self):
        self._engine = _VbdEngine(
            sheet_W=self._sheet0,
            triangles=self._tris,
            grasped=self._grasped,
            grippers_W0=self._grippers_W0,
            colliders=self._colliders,
            settings=self._settings,
            friction=self._friction,
            time_step=self._dt,
            bending=self._bending,
        )
        return self._engine


def _leave_out_of_contact_pairs(wp, pipeline, left_out: dict) -> None:
    """Leaves shapes out of the pipeline's edge or face contact passes
    (newton sets those pairs up for every shape): `left_out` maps a pair
    list's name (CONTACT_ELEMENTS) to the shape indices to drop from it.
    Raises if this newton keeps its pairs elsewhere."""
    for name, shapes in left_out.items():
        pairs = getattr(pipeline, name, None)
        if pairs is None or pairs.dtype != wp.vec2i:
            raise RuntimeError(
                f"newton's CollisionPipeline has no {name} (vec2i) to leave "
                "shapes out of; set cloth.vbd.table_contact: surface"
            )
        p = pairs.numpy()
        keep = ~np.isin(p[:, 1], shapes)
        setattr(pipeline, name, wp.array(p[keep], dtype=wp.vec2i, device=pairs.device))


class _VbdEngine:
    """The newton model, solver and captured step behind ClothSimulator."""

    def __init__(
        self,
        *,
        sheet_W,
        triangles,
        grasped,
        grippers_W0,
        colliders,
        settings: VbdConfig,
        friction: float,
        time_step,
        bending=None,
    ):
        wp = _init_warp()
        import newton
        from newton.solvers import SolverVBD

        self._wp = wp
        self._dt = time_step
        self._s = settings
        builder = newton.ModelBuilder(gravity=(0.0, 0.0, -9.81))
        left_out = {}  # pair list -> shapes the cloth's edges or faces skip
        for box in colliders:
            cfg = newton.ModelBuilder.ShapeConfig(
                mu=box.friction,
                ke=settings.contact_stiffness,
                kd=settings.contact_damping,
            )
            p = box.X_WB.translation()
            q = box.X_WB.rotation().ToQuaternion()  # w, x, y, z
            xform = wp.transform(wp.vec3(*p), wp.quat(q.x(), q.y(), q.z(), q.w()))
            if box.shape == "cylinder":
                shape = builder.add_shape_cylinder(
                    -1,
                    xform=xform,
                    radius=box.size[0] / 2,
                    half_height=box.size[2] / 2,
                    cfg=cfg,
                )
            else:
                shape = builder.add_shape_box(
                    -1,
                    xform=xform,
                    hx=box.size[0] / 2,
                    hy=box.size[1] / 2,
                    hz=box.size[2] / 2,
                    cfg=cfg,
                )
            for name in CONTACT_ELEMENTS[box.contact]:
                left_out.setdefault(name, []).append(shape)
        builder.add_cloth_mesh(
            pos=wp.vec3(0.0, 0.0, 0.0),
            rot=wp.quat_identity(),
            scale=1.0,
            vel=wp.vec3(0.0, 0.0, 0.0),
            vertices=[wp.vec3(*v) for v in sheet_W],
            indices=np.asarray(triangles).ravel().tolist(),
            density=settings.areal_density,
            tri_ke=settings.stretch_stiffness,
            tri_ka=settings.area_stiffness,
            tri_kd=settings.stretch_damping,
            # newton's dihedral bending, or none where this class adds the
            # quadratic bending (`bending`) as an external force.
            edge_ke=settings.bending_stiffness if bending is None else 0.0,
            edge_kd=ResolvedBendingDamping(settings) if bending is None else 0.0,
            particle_radius=settings.contact_distance,
        )
        builder.color(include_bending=True)
        model = builder.finalize(device="cpu", requires_grad=False)
        model.soft_contact_ke = settings.contact_stiffness
        model.soft_contact_kd = settings.contact_damping
        model.soft_contact_mu = friction
        self._model = model
        self._solver = SolverVBD(model, iterations=settings.iterations)
        self._pipeline = newton.CollisionPipeline(
            model,
            soft_contact_gap=settings.contact_distance,
            enable_rigid_soft_full_surface_contact=settings.surface_contact,
        )
        if settings.surface_contact and left_out:
            _leave_out_of_contact_pairs(wp, self._pipeline, left_out)
        self._contacts = self._pipeline.contacts()
        self._states = [model.state(), model.state()]
        self._control = model.control()

        idx = np.concatenate([grasped[s] for s in SIDES]).astype(np.int32)
        side = np.concatenate(
            [np.full(len(grasped[s]), i, np.int32) for i, s in enumerate(SIDES)]
        )
        self._held_idx = idx
        self._free_flags = model.particle_flags.numpy().copy()
        self._free_mass = model.particle_mass.numpy().copy()
        self._free_inv_mass = model.particle_inv_mass.numpy().copy()
        self._idx = wp.array(idx, dtype=wp.int32, device="cpu")
        self._side = wp.array(side, dtype=wp.int32, device="cpu")
        self._offsets = wp.zeros(len(idx), dtype=wp.vec3, device="cpu")
        self._start = wp.zeros(2, dtype=wp.vec3, device="cpu")
        self._end = wp.zeros(2, dtype=wp.vec3, device="cpu")
        self._holding = wp.zeros(1, dtype=wp.int32, device="cpu")
        # Each held particle keeps its rest offset from its gripper.
        g0 = np.stack([grippers_W0[s] for s in SIDES])
        self._offsets.numpy()[:] = np.asarray(sheet_W)[idx] - g0[side]
        self._rest_edge = wp.array([g0[1] - g0[0]], dtype=wp.vec3, device="cpu")
        self._box_p = wp.array(
            np.array([b.X_WB.translation() for b in colliders]).reshape(-1, 3),
            dtype=wp.vec3,
            device="cpu",
        )
        self._box_R = wp.array(
            np.array([b.X_WB.rotation().matrix() for b in colliders]).reshape(-1, 3, 3),
            dtype=wp.mat33,
            device="cpu",
        )
        self._box_half = wp.array(
            np.array([np.asarray(b.size) / 2 for b in colliders]).reshape(-1, 3),
            dtype=wp.vec3,
            device="cpu",
        )
        self._round = wp.array(
            np.array([b.shape == "cylinder" for b in colliders], np.int32),
            dtype=wp.int32,
            device="cpu",
        )
        self._n = len(sheet_W)
        self._hold = _hold_kernel(wp)
        self._bend = None
        if bending is not None:
            stencils, weights, stiffness, damping = bending
            self._bend = [
                wp.array(stencils, dtype=wp.int32, device="cpu"),
                wp.array(weights, dtype=float, device="cpu"),
                wp.array(stiffness, dtype=float, device="cpu"),
                wp.array(damping, dtype=float, device="cpu"),
            ]
        self._graph = None
        self._held = None

    def _set_held(self, held: bool) -> None:
        if held == self._held:
            return
        m = self._model
        flags = self._free_flags.copy()
        mass = self._free_mass.copy()
        inv_mass = self._free_inv_mass.copy()
        if held:
            from newton import ParticleFlags

            flags[self._held_idx] &= ~int(ParticleFlags.ACTIVE)
            mass[self._held_idx] = 0.0
            inv_mass[self._held_idx] = 0.0
        m.particle_flags.numpy()[:] = flags
        m.particle_mass.numpy()[:] = mass
        m.particle_inv_mass.numpy()[:] = inv_mass
        self._holding.numpy()[0] = 1 if held else 0
        self._held = held

    def _simulate(self):
        wp = self._wp
        n = self._s.substeps
        h = self._dt / n
        for k in range(n):
            s0, s1 = self._states[k % 2], self._states[(k + 1) % 2]
            wp.launch(
                self._hold,
                dim=len(self._held_idx),
                inputs=[
                    self._idx,
                    self._side,
                    self._offsets,
                    self._start,
                    self._end,
                    self._rest_edge,
                    self._holding,
                    float(k + 1) / n,
                    1.0 / n,
                    1.0 / self._dt,
                    int(self._s.grasp_turns),
                    self._box_p,
                    self._box_R,
                    self._box_half,
                    self._round,
                    s0.particle_q,
                    s0.particle_qd,
                ],
                device="cpu",
            )
            s0.clear_forces()
            if self._bend is not None:
                wp.launch(
                    _bend_kernel(wp),
                    dim=self._bend[0].shape[0],
                    inputs=[*self._bend, s0.particle_q, s0.particle_qd],
                    outputs=[s0.particle_f],
                    device="cpu",
                )
            self._pipeline.collide(s0, self._contacts)
            self._solver.step(s0, s1, self._control, self._contacts, h)

    def step(self, x, g_start, g_end, *, held: bool):
        wp = self._wp
        s0 = self._states[0]

        def load():  # the Context's state into newton's (zero-copy views)
            s0.particle_q.numpy()[:] = x[: 3 * self._n].reshape(-1, 3)
            s0.particle_qd.numpy()[:] = x[3 * self._n :].reshape(-1, 3)

        self._set_held(held)
        load()
        self._start.numpy()[:] = g_start.reshape(2, 3)
        self._end.numpy()[:] = g_end.reshape(2, 3)
        if self._graph is None:
            self._simulate()  # compiles and warms up the kernels
            load()
            with wp.ScopedCapture(device="cpu") as capture:
                self._simulate()
            self._graph = capture.graph
        wp.capture_launch(self._graph)
        return (
            self._states[0].particle_q.numpy().copy(),
            self._states[0].particle_qd.numpy().copy(),
        )
