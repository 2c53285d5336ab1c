"""Argument checks of the reference projection and its adjoint: each failure a ValueError naming the argument."""

from __future__ import annotations

import math

import numpy as np


def float_array(name: str, value, shape: tuple) -> np.ndarray:
    """``value`` as a finite float64 array of ``shape`` (None: any length), else ValueError naming ``name``."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name} must be a float array of shape {shape}: {err}") from None
    if arr.size == 0 and len(shape) == 2 and shape[0] is None:
        arr = arr.reshape(0, shape[1])
    if arr.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, arr.shape)):
        raise ValueError(f"{name} must have shape {tuple('?' if s is None else s for s in shape)}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise ValueError(f"{name} has a non-finite entry at {tuple(int(i) for i in bad)}")
    return arr


def check_inputs(x_hat, mass, fixed, obstacle_x, nodes, weights, normals, thickness):
    """``project``'s problem data checked and converted (float64, int64 nodes, bool ``fixed``, obstacle_x (V, 3))."""
    x_hat = float_array("x_hat", x_hat, (None, 3))
    n = x_hat.shape[0]
    mass = float_array("mass", mass, (n,))
    if fixed is None:
        fixed = np.zeros(n, dtype=bool)
    fixed = np.asarray(fixed)
    if fixed.shape != (n,):
        raise ValueError(f"fixed must have shape ({n},), got {fixed.shape}")
    if fixed.dtype != bool:
        if not (np.issubdtype(fixed.dtype, np.integer) and np.all((fixed == 0) | (fixed == 1))):
            raise ValueError(f"fixed must be a boolean array, got dtype {fixed.dtype}")
        fixed = fixed.astype(bool)
    bad = np.flatnonzero(~fixed & ~(mass > 0.0))
    if bad.size:
        raise ValueError(f"mass must be > 0 for every free particle; particle {int(bad[0])} has {mass[bad[0]]}")
    obstacle_x = float_array("obstacle_x", np.zeros((0, 3)) if obstacle_x is None else obstacle_x, (None, 3))
    V = obstacle_x.shape[0]
    nodes_arr = np.asarray(nodes)
    if nodes_arr.size == 0:
        nodes_arr = nodes_arr.reshape(0, 4)
    if nodes_arr.ndim != 2 or nodes_arr.shape[1] != 4:
        raise ValueError(f"nodes must have shape (m, 4), got {nodes_arr.shape}")
    if nodes_arr.size and not np.issubdtype(nodes_arr.dtype, np.integer):
        raise ValueError(f"nodes must be an integer array, got dtype {nodes_arr.dtype}")
    nodes_arr = nodes_arr.astype(np.int64)
    m = nodes_arr.shape[0]
    out = (nodes_arr < 0) | (nodes_arr >= n + V)
    if out.any():
        j, a = np.argwhere(out)[0]
        raise ValueError(f"nodes[{j}, {a}] = {nodes_arr[j, a]} is outside [0, {n + V}) "
                         f"({n} particles + {V} obstacle vertices)")
    weights = float_array("weights", weights, (m, 4))
    normals = float_array("normals", normals, (m, 3))
    if np.ndim(thickness) == 0:
        try:
            thickness = float(thickness)
        except (TypeError, ValueError):
            raise ValueError(f"thickness must be a number or an array of one gap per contact, got {thickness!r}") \
                from None
        if not math.isfinite(thickness) or thickness <= 0.0:
            raise ValueError(f"thickness must be finite and > 0, got {thickness}")
        thickness = np.full(m, thickness)
    else:  # one target gap per contact (the stage's: no more than the pair's gap at the start)
        thickness = float_array("thickness", thickness, (m,))
    return x_hat, mass, fixed, obstacle_x, nodes_arr, weights, normals, thickness


def check_options(tol, active_tol, max_iterations, warm_sweeps) -> tuple[float, float]:
    """Check the solver options of ``project``; returns (tol, active_tol) as floats."""
    for name, val in (("tol", tol), ("active_tol", active_tol)):
        try:
            ok = math.isfinite(float(val)) and float(val) > 0.0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ValueError(f"{name} must be finite and > 0, got {val!r}")
    for name, val, low in (("max_iterations", max_iterations, 1), ("warm_sweeps", warm_sweeps, 0)):
        if isinstance(val, bool) or not isinstance(val, (int, np.integer)) or val < low:
            raise ValueError(f"{name} must be an integer >= {low}, got {val!r}")
    return float(tol), float(active_tol)
