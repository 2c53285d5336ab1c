"""Rigid placements on the host: unit quaternions (x, y, z, w) and transforms (px, py, pz [m], qx, qy, qz, qw)."""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "IDENTITY_TRANSFORM",
    "QUAT_UNIT_TOL",
    "check_quat",
    "compose",
    "placement",
    "quat_from_matrix",
    "quat_to_matrix",
    "slerp",
    "transform_points",
]

QUAT_UNIT_TOL = 1.0e-6
"""Largest accepted | |q| - 1 | of a rotation quaternion; beyond it a quaternion is an error, not renormalised."""

IDENTITY_TRANSFORM = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
"""The identity placement (px, py, pz, qx, qy, qz, qw)."""


def check_quat(what: str, q) -> np.ndarray:
    """``q`` as a float64 (4,) array; ValueError naming ``what`` unless it is a finite unit quaternion."""
    q = np.asarray(q, dtype=np.float64)
    if q.shape != (4,):
        raise ValueError(f"{what}: a quaternion needs 4 components (x, y, z, w), got shape {q.shape}")
    if not np.all(np.isfinite(q)):
        raise ValueError(f"{what}: quaternion has a non-finite component: {q.tolist()}")
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUAT_UNIT_TOL:
        raise ValueError(
            f"{what}: quaternion {q.tolist()} has norm {norm:.9g}; it must be a unit quaternion (x, y, z, w) "
            f"within {QUAT_UNIT_TOL:g}"
        )
    return q


def quat_to_matrix(q) -> np.ndarray:
    """Rotation matrix (3, 3) of a unit quaternion (x, y, z, w)."""
    x, y, z, w = np.asarray(q, dtype=np.float64)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_from_matrix(R) -> np.ndarray:
    """Unit quaternion (x, y, z, w) with ``w >= 0`` of a rotation matrix ``R``; ValueError unless ``R`` is 3x3,
    orthonormal within 1e-6, with determinant +1."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"a rotation matrix must have shape (3, 3), got {R.shape}")
    if not np.all(np.isfinite(R)):
        raise ValueError("rotation matrix has a non-finite entry")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0.0:
        raise ValueError("rot must be a rotation matrix (orthonormal within 1e-6, determinant +1, no reflection)")
    # Shepperd's method: branch on the largest of (trace, diagonal) for a well-conditioned square root.
    tr = np.trace(R)
    d = np.diag(R)
    k = int(np.argmax([tr, d[0], d[1], d[2]]))
    if k == 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif k == 1:
        s = 2.0 * math.sqrt(1.0 + d[0] - d[1] - d[2])
        q = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif k == 2:
        s = 2.0 * math.sqrt(1.0 + d[1] - d[0] - d[2])
        q = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + d[2] - d[0] - d[1])
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0.0 else q


def slerp(q0: np.ndarray, q1: np.ndarray, s: float) -> np.ndarray:
    """Spherical linear interpolation along the shorter arc (q and -q are the same rotation)."""
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 1.0 - 1e-12:  # (nearly) the same rotation: the slerp weights are 0/0
        q = (1.0 - s) * q0 + s * q1
    else:
        theta = math.acos(min(dot, 1.0))
        sin_theta = math.sin(theta)
        q = (math.sin((1.0 - s) * theta) * q0 + math.sin(s * theta) * q1) / sin_theta
    return q / np.linalg.norm(q)


def placement(what: str, pos, rot) -> np.ndarray:
    """(7,) transform from a position [m] and a rotation (None, a 3x3 matrix or a quaternion (x, y, z, w))."""
    p = np.asarray(pos, dtype=np.float64)
    if p.shape != (3,):
        raise ValueError(f"{what}: pos must have 3 components, got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{what}: pos has a non-finite component: {p.tolist()}")
    if rot is None:
        q = np.array([0.0, 0.0, 0.0, 1.0])
    else:
        r = np.asarray(rot, dtype=np.float64)
        if r.shape == (3, 3):
            try:
                q = quat_from_matrix(r)
            except ValueError as exc:
                raise ValueError(f"{what}: {exc}") from None
        elif r.shape == (4,):
            q = check_quat(f"{what}: rot", r)
            q = q / np.linalg.norm(q)  # within QUAT_UNIT_TOL already: remove the rounding, not an error
        else:
            raise ValueError(
                f"{what}: rot must be a 3x3 rotation matrix or a quaternion (x, y, z, w), got shape {r.shape}"
            )
    return np.concatenate([p, q])


def transform_points(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (N, 3) [m] moved by a (7,) transform."""
    return points @ quat_to_matrix(transform[3:]).T + transform[:3]


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Transform ``a * b`` (apply b, then a) as (7,)."""
    Ra = quat_to_matrix(a[3:])
    ax, ay, az, aw = a[3:]
    bx, by, bz, bw = b[3:]
    q = np.array(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ]
    )
    return np.concatenate([Ra @ b[:3] + a[:3], q])
