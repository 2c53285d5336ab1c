"""Host precompute of ARCSim's stretching stiffness lookup (``dde.cpp``, SPEC.md §1.2): per cell of the 30^3 grid
over (G00, G11, |G01|), the weights of the three table rows its bilinear sample reads."""

import functools

import numpy as np

from warpcloth.kernels.stretching import LUT_SIZE


@functools.cache
def stretching_lut() -> tuple[np.ndarray, np.ndarray]:
    """``(weights, row)``: weights (30^3, 3) of table rows (0, row+1, row+2) and ``row`` (30^3,); cell (i, j, k)
    sits at G00 = i/30 - 0.25, G11 = j/30 - 0.25, |G01| = k/30."""
    n = LUT_SIZE
    i, j, k = np.meshgrid(np.arange(n), np.arange(n), np.arange(n), indexing="ij")
    c00 = 0.5 + 2.0 * i / n
    c11 = 0.5 + 2.0 * j / n
    c01 = 2.0 * k / n
    # largest eigenvalue of the right Cauchy-Green tensor and its eigenvector (w - C11, C01)
    w = 0.5 * (c00 + c11 + np.sqrt(4.0 * c01**2 + (c00 - c11) ** 2))
    v0 = w - c11
    v1 = c01
    on_axis = k == 0
    v0 = np.where(on_axis, np.where(i >= j, 1.0, 0.0), v0)
    v1 = np.where(on_axis, np.where(i >= j, 0.0, 1.0), v1)
    angle = np.abs(np.arctan2(v1, v0) / np.pi) * 8.0  # 0..4 over 0..90 degrees
    strain = np.clip((np.sqrt(w) - 1.0) * 6.0, 0.0, 1.0)  # border padding of the 2-row strain axis
    col = np.minimum(np.floor(angle).astype(np.int32), 3)
    frac = angle - col
    weights = np.stack([1.0 - strain, strain * (1.0 - frac), strain * frac], axis=-1)
    return weights.reshape(-1, 3), col.reshape(-1).astype(np.int32)


def fold_direction(du: np.ndarray) -> np.ndarray:
    """Bending-table direction index in [0, 2] (0, 45, 90 deg, folded, SPEC §1.3) of edge vectors ``du`` (..., 2)."""
    a = np.abs(np.arctan2(du[..., 1], du[..., 0]) * 4.0 / np.pi) % 4.0
    return np.where(a > 2.0, 4.0 - a, a)
