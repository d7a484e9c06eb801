"""A thin tetrahedral slab for the FEM cloth, generated in memory as .vtk."""

import dataclasses as dc
import itertools

import numpy as np
from fabric_imitation.learning.state import boundary_grid_indices


@dc.dataclass(frozen=True)
class ClothMesh:
    """Slab mesh in the cloth frame C (centre of the slab, grasped edge at -y).

    Attributes:
        vertices: (N, 3) rest positions p_CV.
        tetrahedra: (K, 4) vertex indices, positively oriented.
        grid: (nx, ny, nz) vertex index of each grid node.
    """

    vertices: np.ndarray
    tetrahedra: np.ndarray
    grid: np.ndarray

    @property
    def top_layer(self) -> np.ndarray:
        """(nx, ny) indices of the vertices on the top face (seen by the camera)."""
        return self.grid[:, :, -1]

    def keypoint_vertices(self, m: int) -> np.ndarray:
        """(m,) indices of the top-face vertices that are the m keypoints."""
        nx, ny = self.top_layer.shape
        return np.array(
            [self.top_layer[i, j] for i, j in boundary_grid_indices(m, nx, ny)]
        )

    def surface_edges(self) -> np.ndarray:
        """(E, 2) in-plane grid edges of the top layer (for strain checks)."""
        top = self.top_layer
        return np.concatenate(
            [
                np.stack([top[:-1, :].ravel(), top[1:, :].ravel()], 1),
                np.stack([top[:, :-1].ravel(), top[:, 1:].ravel()], 1),
            ]
        )

    def to_vtk(self) -> str:
        """Legacy-format ASCII .vtk (UNSTRUCTURED_GRID of tetrahedra)."""
        lines = [
            "# vtk DataFile Version 3.0",
            "fabric-imitation cloth slab",
            "ASCII",
            "DATASET UNSTRUCTURED_GRID",
            f"POINTS {len(self.vertices)} double",
        ]
        lines += [f"{x:.7f} {y:.7f} {z:.7f}" for x, y, z in self.vertices]
        n = len(self.tetrahedra)
        lines.append(f"CELLS {n} {5 * n}")
        lines += ["4 " + " ".join(map(str, t)) for t in self.tetrahedra]
        lines.append(f"CELL_TYPES {n}")
        lines += ["10"] * n
        return "\n".join(lines) + "\n"


def TopTriangles(top_grid: np.ndarray, checkerboard: bool = False) -> np.ndarray:
    """(T, 3) counter-clockwise triangles of the cloth's top face from its
    (nx, ny) vertex grid, two per cell: every cell split along the same
    diagonal, or with `checkerboard` the cells' diagonals alternating as in
    the slab's tetrahedra (MakeClothMesh), so the sheet has no preferred
    shear or fold direction (`cloth.vbd.triangulation`)."""
    a = top_grid[:-1, :-1]
    b = top_grid[1:, :-1]
    c = top_grid[1:, 1:]
    d = top_grid[:-1, 1:]
    i, j = np.indices(a.shape)
    mirrored = (((i + j) % 2 == 1) & checkerboard).ravel()
    a, b, c, d = (v.ravel() for v in (a, b, c, d))
    first = np.where(mirrored[:, None], np.stack([a, b, d], 1), np.stack([a, b, c], 1))
    second = np.where(mirrored[:, None], np.stack([b, c, d], 1), np.stack([a, c, d], 1))
    return np.concatenate([first, second])


def MakeClothMesh(
    size: list[float], thickness: float, resolution: list[int]
) -> ClothMesh:
    """Slab of size[0] x size[1] x thickness with resolution = (nx, ny, nz) vertices.

    Each grid cell is split into 6 tetrahedra around one of its diagonals; the
    diagonal is mirrored in alternate cells so the slab has no preferred shear
    direction (a uniform split makes a flat cloth on a table bulge twice as
    much under friction on Drake 1.58).
    """
    nx, ny, nz = resolution
    xs = np.linspace(-size[0] / 2, size[0] / 2, nx)
    ys = np.linspace(-size[1] / 2, size[1] / 2, ny)
    zs = np.linspace(-thickness / 2, thickness / 2, nz)
    grid = np.arange(nx * ny * nz).reshape(nx, ny, nz)
    vertices = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), -1).reshape(-1, 3)
    tets = []
    for i, j, k in itertools.product(range(nx - 1), range(ny - 1), range(nz - 1)):
        flip = np.array([i % 2, j % 2, k % 2])
        base = np.array([i, j, k]) + flip
        step = 1 - 2 * flip
        for order in itertools.permutations(range(3)):
            node = base.copy()
            tet = [grid[tuple(node)]]
            for axis in order:
                node[axis] += step[axis]
                tet.append(grid[tuple(node)])
            a, b, c, d = vertices[tet]
            if np.dot(np.cross(b - a, c - a), d - a) < 0:
                tet[1], tet[2] = tet[2], tet[1]
            tets.append(tet)
    return ClothMesh(vertices=vertices, tetrahedra=np.array(tets), grid=grid)
