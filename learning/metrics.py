"""Evaluation metrics: Chamfer distance between fabric point clouds from depth
within the mask (paper Section V-C), 200 points each."""

import numpy as np
import torch

CLOUD_POINTS = 200


def cloud_from_depth(
    camera,
    depth: np.ndarray,
    mask: np.ndarray,
    rng: np.random.Generator,
    n: int = CLOUD_POINTS,
) -> np.ndarray:
    """(n, 3) world points of the fabric: back-projected depth inside the mask,
    down-sampled evenly (every k-th pixel in raster order, with a random
    phase); fewer if the mask is smaller than n pixels."""
    v, u = np.nonzero((mask > 0) & np.isfinite(depth))
    if len(v) == 0:
        return np.zeros((0, 3))
    step = max(1, len(v) // n)
    start = int(rng.integers(step))
    v, u = v[start::step][:n], u[start::step][:n]
    rays = camera.rays_W[torch.as_tensor(v), torch.as_tensor(u)].numpy()
    return camera.p_WC.numpy() + depth[v, u][:, None] * rays


def chamfer_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Mean squared nearest-neighbour distance, both ways [m^2]."""
    if len(a) == 0 or len(b) == 0:
        return float("inf")
    d = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)
    return float(d.min(1).mean() + d.min(0).mean())


def raster_iou(a: np.ndarray, b: np.ndarray, cell: float = 0.001) -> float:
    """IoU of the regions two polygons (K, 2) [m] enclose, filled on a grid of
    `cell` metres (even-odd rule). Bounded in [0, 1] for any polygon, also a
    self-crossing one (a twisted cloth's keypoint outline), where the exact
    signed-area formula of `learning.polygon.iou` is not."""
    import cv2

    a, b = np.asarray(a, float), np.asarray(b, float)
    lo = np.minimum(a.min(0), b.min(0)) - 2 * cell
    hi = np.maximum(a.max(0), b.max(0)) + 2 * cell
    w, h = (np.ceil((hi - lo) / cell).astype(int) + 1).tolist()

    def fill(p):
        image = np.zeros((h, w), np.uint8)
        points = np.round((p - lo) / cell).astype(np.int32)
        cv2.fillPoly(image, [points], 1)
        return image.astype(bool)

    ma, mb = fill(a), fill(b)
    union = np.logical_or(ma, mb).sum()
    return float(np.logical_and(ma, mb).sum() / union) if union else 0.0
