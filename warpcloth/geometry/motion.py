"""Keyframed rigid motion on the host (an obstacle's scripted motion); quaternions in Warp's (x, y, z, w) order."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from warpcloth.geometry.transforms import check_quat, slerp

__all__ = ["RigidMotion"]


@dataclass
class RigidMotion:
    """Piecewise-linear translation and slerp rotation (shorter arc) between keys, the nearest key's outside them;
    from arrays (validated, raising ValueError) or :meth:`from_keyframes`."""

    times: np.ndarray
    """Key times [s], strictly increasing, shape (K,), K >= 1."""
    translations: np.ndarray
    """Translation at each key [m], shape (K, 3)."""
    rotations: np.ndarray
    """Rotation at each key as a unit quaternion (x, y, z, w), shape (K, 4); not renormalised."""

    def __post_init__(self):
        self.times = np.asarray(self.times, dtype=np.float64)
        self.translations = np.asarray(self.translations, dtype=np.float64)
        self.rotations = np.asarray(self.rotations, dtype=np.float64)
        k = self.times.shape[0] if self.times.ndim == 1 else -1
        if k < 1:
            raise ValueError(f"motion: times must have shape (K,) with K >= 1 keyframes, got {self.times.shape}")
        if self.translations.shape != (k, 3):
            raise ValueError(f"motion: translations must have shape ({k}, 3), got {self.translations.shape}")
        if self.rotations.shape != (k, 4):
            raise ValueError(f"motion: rotations must have shape ({k}, 4), got {self.rotations.shape}")
        for i in range(k):
            if not math.isfinite(self.times[i]):
                raise ValueError(f"motion keyframe {i}: time is not finite: {self.times[i]}")
            if i and self.times[i] <= self.times[i - 1]:
                raise ValueError(
                    f"motion keyframe {i}: key times must be strictly increasing, got {self.times[i]} after "
                    f"{self.times[i - 1]}"
                )
            if not np.all(np.isfinite(self.translations[i])):
                raise ValueError(f"motion keyframe {i}: translation is not finite: {self.translations[i].tolist()}")
            check_quat(f"motion keyframe {i}: rotation", self.rotations[i])

    @classmethod
    def from_keyframes(cls, keyframes) -> RigidMotion:
        """A motion from ``[(time [s], (tx, ty, tz) [m], (qx, qy, qz, qw)), ...]``; ValueError naming a malformed,
        non-finite, out-of-order or non-unit keyframe."""
        keys = list(keyframes)
        if not keys:
            raise ValueError("motion needs at least one (time, translation, quaternion) keyframe")
        times, trans, rots = [], [], []
        for i, key in enumerate(keys):
            if isinstance(key, (str, bytes)) or len(key) != 3:
                raise ValueError(f"motion keyframe {i}: expected (time, (tx, ty, tz), (qx, qy, qz, qw)), got {key!r}")
            t, tr, q = key
            tr, q = np.asarray(tr, dtype=np.float64), np.asarray(q, dtype=np.float64)
            if tr.shape != (3,):
                raise ValueError(f"motion keyframe {i}: translation needs 3 components, got shape {tr.shape}")
            if q.shape != (4,):
                raise ValueError(f"motion keyframe {i}: rotation needs 4 components (x, y, z, w), got shape {q.shape}")
            times.append(float(t))
            trans.append(tr)
            rots.append(q)
        return cls(np.array(times), np.array(trans), np.array(rots))

    @property
    def key_count(self) -> int:
        """Number of keyframes K."""
        return int(self.times.shape[0])

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Translation (3,) [m] and unit quaternion (4,) at time ``t`` [s]."""
        t = float(t)
        if not math.isfinite(t):
            raise ValueError(f"motion: time must be finite, got {t}")
        if t <= self.times[0]:
            return self.translations[0].copy(), self.rotations[0].copy()
        if t >= self.times[-1]:
            return self.translations[-1].copy(), self.rotations[-1].copy()
        i = int(np.searchsorted(self.times, t, side="right")) - 1
        s = (t - self.times[i]) / (self.times[i + 1] - self.times[i])
        tr = (1.0 - s) * self.translations[i] + s * self.translations[i + 1]
        return tr, slerp(self.rotations[i], self.rotations[i + 1], s)

    def transform_at(self, t: float) -> np.ndarray:
        """The motion at time ``t`` as a (7,) transform (tx, ty, tz, qx, qy, qz, qw)."""
        tr, q = self.at(t)
        return np.concatenate([tr, q])
