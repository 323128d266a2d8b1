"""Per-trial metrics computed from the recorded ground truth (numpy, vectorised over time)."""

from __future__ import annotations

import numpy as np


def box_corners(x, y, yaw, length, width) -> np.ndarray:
    """Corners (T, 4, 2) of oriented rectangles centred at (x, y), counter-clockwise."""
    x, y, yaw = (np.asarray(v, np.float64) for v in (x, y, yaw))
    length, width = np.broadcast_to(length, x.shape), np.broadcast_to(width, x.shape)
    c, s = np.cos(yaw), np.sin(yaw)
    hx, hy = length / 2, width / 2
    local = np.array([[1, -1], [1, 1], [-1, 1], [-1, -1]], np.float64)  # (4, 2) signs
    lx, ly = local[None, :, 0] * hx[:, None], local[None, :, 1] * hy[:, None]
    return np.stack([x[:, None] + c[:, None] * lx - s[:, None] * ly,
                     y[:, None] + s[:, None] * lx + c[:, None] * ly], -1)


def _point_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances (T, P, S) from points p (T, P, 2) to segments a->b (T, S, 2)."""
    d = (b - a)[:, None, :, :]
    ap = p[:, :, None, :] - a[:, None, :, :]
    t = np.clip((ap * d).sum(-1) / np.maximum((d * d).sum(-1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(ap - d * t[..., None], axis=-1)


def _overlap(ca: np.ndarray, cb: np.ndarray) -> np.ndarray:
    """Separating-axis test of two convex quads per row: (T,) bool, True = they intersect."""
    sep = np.zeros(ca.shape[0], bool)
    for poly in (ca, cb):
        for k in range(2):  # a rectangle has two distinct edge normals
            e = poly[:, k + 1] - poly[:, k]
            n = np.stack([-e[:, 1], e[:, 0]], -1)
            pa, pb = (ca * n[:, None]).sum(-1), (cb * n[:, None]).sum(-1)
            sep |= (pa.max(1) < pb.min(1)) | (pb.max(1) < pa.min(1))
    return ~sep


def footprint_gap(ca: np.ndarray, cb: np.ndarray) -> np.ndarray:
    """Distance (T,) between two rectangles per row given their corners (T, 4, 2); 0 if touching."""
    ea, eb = np.roll(ca, -1, axis=1), np.roll(cb, -1, axis=1)
    d = np.minimum(_point_segment(ca, cb, eb).min((1, 2)), _point_segment(cb, ca, ea).min((1, 2)))
    return np.where(_overlap(ca, cb), 0.0, d)
