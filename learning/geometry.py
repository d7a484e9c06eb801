"""Camera geometry and the canonical frame of a cloth state (torch, batched).

Camera: Drake's convention, X right, Y down, Z along the optical axis; pixel
(u, v) is (column, row).

Canonical frame of a state: origin at the midpoint of the grasped corners
s1, s2 on the table plane (z = 0), x axis along s2 - s1 projected on the table.
Dynamics are learned in this frame, which makes them independent of where the
cloth lies on the table and how it is turned about the vertical, hence of the
object frame a task is expressed in. Height is kept:
gravity and the table break that symmetry.
"""

import numpy as np
import torch
from fabric_imitation.learning.demo_io import CameraModel
from fabric_imitation.learning.state import corner_indices


class PinholeCamera:
    """Projection and back-projection, in torch, for the camera `model`
    (intrinsics and X_WC)."""

    def __init__(self, model: CameraModel):
        self.model = model
        self.width, self.height = int(model.width), int(model.height)
        fx, fy, cx, cy = model.fx, model.fy, model.cx, model.cy
        self.K = torch.tensor(
            [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float32
        )
        X = torch.as_tensor(np.asarray(model.X_WC), dtype=torch.float32)
        self.R_WC, self.p_WC = X[:3, :3], X[:3, 3]
        v, u = torch.meshgrid(
            torch.arange(self.height, dtype=torch.float32),
            torch.arange(self.width, dtype=torch.float32),
            indexing="ij",
        )
        rays_C = torch.stack([(u - cx) / fx, (v - cy) / fy, torch.ones_like(u)], -1)
        self.rays_W = rays_C @ self.R_WC.T  # (H, W, 3): p_W = p_WC + depth * ray

    def height_map(self, depth: torch.Tensor) -> torch.Tensor:
        """World z of each pixel's surface point, (..., H, W); 0 where no return."""
        d = torch.where(torch.isfinite(depth), depth, torch.zeros_like(depth))
        return self.p_WC[2] + d * self.rays_W[..., 2]

    def project(self, p_W: torch.Tensor) -> torch.Tensor:
        """Pixel coordinates (..., 2) of world points (..., 3)."""
        p_C = (p_W - self.p_WC) @ self.R_WC
        uvw = p_C @ self.K.T
        return uvw[..., :2] / uvw[..., 2:3]

    def back_project(
        self, uv: torch.Tensor, depth: torch.Tensor, mask: torch.Tensor, radius: int = 4
    ) -> torch.Tensor:
        """World points (B, K, 3) at pixel coordinates uv (B, K, 2), reading the
        depth (B, H, W) of the nearest fabric pixel within `radius` (a boundary
        keypoint predicted just off the mask still lands on the cloth); the
        nearest pixel of any kind when the window holds no fabric."""
        B, K, _ = uv.shape
        r = torch.arange(-radius, radius + 1)
        dv, du = torch.meshgrid(r, r, indexing="ij")
        base = uv.round().long()
        cu = (base[..., 0, None] + du.reshape(-1)).clamp(0, self.width - 1)
        cv = (base[..., 1, None] + dv.reshape(-1)).clamp(0, self.height - 1)
        bidx = torch.arange(B)[:, None, None].expand_as(cu)
        on = mask[bidx, cv, cu] > 0
        d2 = (cu - uv[..., 0:1]) ** 2 + (cv - uv[..., 1:2]) ** 2
        d2 = torch.where(on, d2, d2 + 1e6)
        best = d2.argmin(-1, keepdim=True)
        pu = cu.gather(-1, best)[..., 0]
        pv = cv.gather(-1, best)[..., 0]
        z = depth[bidx[..., 0], pv, pu]
        z = torch.where(torch.isfinite(z), z, torch.zeros_like(z))
        # The ray through the sub-pixel location itself, at that pixel's depth.
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        rays_C = torch.stack(
            [
                (uv[..., 0] - cx) / fx,
                (uv[..., 1] - cy) / fy,
                torch.ones_like(uv[..., 0]),
            ],
            -1,
        )
        return self.p_WC + z[..., None] * (rays_C @ self.R_WC.T)


def canonical_frame(S: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Origin (..., 3) and yaw (...) of the canonical frame of states (..., M, 3)."""
    idx = corner_indices(S.shape[-2])
    s1, s2 = S[..., idx["s1"], :], S[..., idx["s2"], :]
    origin = (s1 + s2) / 2
    origin = torch.cat([origin[..., :2], torch.zeros_like(origin[..., 2:])], -1)
    d = s2 - s1
    yaw = torch.atan2(d[..., 1], d[..., 0])
    return origin, yaw


def _rot(yaw: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(yaw), torch.sin(yaw)
    z, o = torch.zeros_like(c), torch.ones_like(c)
    return torch.stack(
        [
            torch.stack([c, -s, z], -1),
            torch.stack([s, c, z], -1),
            torch.stack([z, z, o], -1),
        ],
        -2,
    )


def to_frame(P: torch.Tensor, origin: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    """Points (..., K, 3) into the frame (origin (..., 3), yaw (...))."""
    return (P - origin[..., None, :]) @ _rot(yaw)


def from_frame(
    P: torch.Tensor, origin: torch.Tensor, yaw: torch.Tensor
) -> torch.Tensor:
    return P @ _rot(yaw).transpose(-1, -2) + origin[..., None, :]


def rotate_actions(A: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    """Actions (..., 6) rotated by +yaw (from a frame to its parent)."""
    moves = A.reshape(*A.shape[:-1], 2, 3) @ _rot(yaw).transpose(-1, -2)
    return moves.reshape(A.shape)
