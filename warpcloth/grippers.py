"""Grippers: cloth particles held to a rigid frame by soft handles between a grasp and a release, the frame moving on
a cubic B-spline whose speed and acceleration limits hold for every parameter vector. Why this form:
docs/decisions.md, "Gripper trajectories are B-splines of bounded increments"."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

DEFAULT_GRIPPER_STIFFNESS = 1.0e4
"""A gripper's handle stiffness [N/m] unless given."""
DEFAULT_MAX_YAW_RATE = math.pi
"""A rotating gripper's yaw-rate limit [rad/s] unless given."""
DEFAULT_MAX_YAW_ACCELERATION = 4.0 * math.pi
"""A rotating gripper's yaw-acceleration limit [rad/s^2] unless given."""
_TOL = 1e-9  # relative slack of the checks of scripted knots (their own rounding)


@dataclass(frozen=True, eq=False)
class Gripper:
    """Particles held by stiff handles to a frame that moves on a uniform cubic B-spline of its knots.

    Knot i, at time ``times[i]`` (equally spaced, h apart), is the spline's control point whose weight peaks there
    (the frame passes near it): before ``times[0]`` the frame rests at knot 0, after the last knot it coasts at its
    last velocity. The frame is at ``x_c + c(t)``, x_c the held particles' initial centroid, and turns about +z by
    ``yaw(t)``; the held particles' targets are ``x_c + c(t) + Rz(yaw(t) - yaw(grasp)) (x0 - x_c - c(grasp))``
    (x0: their initial positions), so the grasp takes them where they start. The handles act in the steps that end
    in (grasp, release].

    Args:
        particles: the held particles (model indices).
        times: knot times [s], (K,), K >= 2, equally spaced.
        positions: knot positions [m], (K, 3): the frame's displacement from the held particles' centroid.
        yaw: knot rotations about +z [rad], (K,), or None for a frame that does not turn.
        grasp, release: when the handles take hold and let go [s], grasp < release.
        max_speed, max_acceleration: limits on the frame's speed [m/s] and acceleration [m/s^2], > 0.
        max_yaw_rate, max_yaw_acceleration: limits on the yaw's rate [rad/s] and acceleration [rad/s^2].
        stiffness: the handles' stiffness [N/m].

    Raises:
        ValueError: a bad value, knot times not increasing or not equally spaced, release not after grasp, no
            particle or one twice, or knots whose trajectory breaks a limit (naming the knot)."""

    particles: tuple[int, ...]
    times: np.ndarray
    positions: np.ndarray
    yaw: np.ndarray | None = None
    grasp: float = 0.0
    release: float = math.inf
    max_speed: float = 2.0
    max_acceleration: float = 20.0
    max_yaw_rate: float = DEFAULT_MAX_YAW_RATE
    max_yaw_acceleration: float = DEFAULT_MAX_YAW_ACCELERATION
    stiffness: float = DEFAULT_GRIPPER_STIFFNESS
    name: str = "gripper"

    def __post_init__(self):
        name = self.name
        particles = tuple(int(p) for p in self.particles)
        if not particles:
            raise ValueError(f"{name}: holds no particle")
        if len(set(particles)) != len(particles):
            twice = next(p for k, p in enumerate(particles) if p in particles[:k])
            raise ValueError(f"{name}: particle {twice} is listed twice")
        times = np.asarray(self.times, dtype=np.float64).reshape(-1)
        positions = np.asarray(self.positions, dtype=np.float64)
        if times.size < 2:
            raise ValueError(f"{name}: needs at least 2 knots, got {times.size}")
        if positions.shape != (times.size, 3):
            raise ValueError(f"{name}: knot positions must be ({times.size}, 3), got {positions.shape}")
        for k in range(times.size):
            if not (math.isfinite(times[k]) and np.all(np.isfinite(positions[k]))):
                raise ValueError(f"{name}: knot {k} is not finite")
            if k and times[k] <= times[k - 1]:
                raise ValueError(f"{name}: knot {k} at {times[k]:g} s is not after knot {k - 1} at "
                                 f"{times[k - 1]:g} s (knots in time order)")
        h = times[1] - times[0]
        for k in range(2, times.size):
            if abs(times[k] - (times[0] + k * h)) > 1e-6 * h:
                raise ValueError(f"{name}: knot {k} at {times[k]:g} s; the knots of a gripper are equally spaced "
                                 f"(a uniform B-spline), so it must be at {times[0] + k * h:g} s")
        yaw = None
        if self.yaw is not None:
            yaw = np.asarray(self.yaw, dtype=np.float64).reshape(-1)
            if yaw.shape != times.shape or not np.all(np.isfinite(yaw)):
                raise ValueError(f"{name}: yaw must be {times.size} finite angles [rad], got {yaw.tolist()}")
        for key in ("max_speed", "max_acceleration", "max_yaw_rate", "max_yaw_acceleration"):
            value = float(getattr(self, key))
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name}: {key} must be finite and > 0, got {value}")
        if not (math.isfinite(self.stiffness) and self.stiffness > 0.0):
            raise ValueError(f"{name}: stiffness must be finite and > 0 [N/m], got {self.stiffness}")
        if not math.isfinite(self.grasp) or math.isnan(self.release) or not self.release > self.grasp:
            raise ValueError(f"{name}: release ({self.release:g} s) must come after grasp ({self.grasp:g} s)")
        object.__setattr__(self, "particles", particles)
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "positions", positions)
        object.__setattr__(self, "yaw", yaw)
        self._check_limits()

    # -- the spline ----------------------------------------------------------------------------------------------
    @property
    def knot_count(self) -> int:
        return int(self.times.size)

    @property
    def knot_interval(self) -> float:
        """h [s], the time between knots."""
        return float(self.times[1] - self.times[0])

    @property
    def rotates(self) -> bool:
        return self.yaw is not None

    @property
    def n_params(self) -> int:
        """Free numbers of :meth:`control_points`: 3 (and 1 for the yaw) per knot after the first."""
        return (self.knot_count - 1) * (4 if self.rotates else 3)

    def weights(self, times) -> np.ndarray:
        """W (len(times), K): the frame's position at ``times`` [s] is ``W @ control points`` (the padding before
        the first knot and the extrapolation after the last included)."""
        times = np.asarray(times, dtype=np.float64).reshape(-1)
        K, h = self.knot_count, self.knot_interval
        s = (times - self.times[0]) / h
        m = np.floor(s)
        u = s - m
        basis = np.stack([(1 - u) ** 3, 3 * u ** 3 - 6 * u ** 2 + 4, -3 * u ** 3 + 3 * u ** 2 + 3 * u + 1, u ** 3],
                         axis=1) / 6.0
        W = np.zeros((times.size, K))
        for c in range(4):
            i = m.astype(np.int64) - 1 + c  # the control point this basis function weighs
            below, above = i < 0, i > K - 1
            inside = ~below & ~above
            rows = np.arange(times.size)
            np.add.at(W, (rows[inside], i[inside]), basis[inside, c])
            np.add.at(W, (rows[below], 0), basis[below, c])
            # past the last knot: P_{K-1} + n (P_{K-1} - P_{K-2})
            n = (i - (K - 1))[above]
            np.add.at(W, (rows[above], K - 1), basis[above, c] * (1 + n))
            np.add.at(W, (rows[above], K - 2), -basis[above, c] * n)
        return W

    def default_params(self) -> np.ndarray:
        """The parameters of the scripted knots (:meth:`control_points` returns them)."""
        return self.params_of(self.positions)

    def params_of(self, positions, yaw=None) -> np.ndarray:
        """The parameters whose :meth:`control_points` are ``positions`` (K, 3) [m] and ``yaw`` (K,) [rad] (None:
        the scripted yaws) where those keep the limits, else of their projection into them; knot 0 is the
        gripper's own (not a parameter). ValueError for a bad shape or a value not finite."""
        P = np.array(positions, dtype=np.float64)
        if P.shape != self.positions.shape or not np.all(np.isfinite(P)):
            raise ValueError(f"{self.name}: knot positions must be {self.positions.shape} finite numbers, got "
                             f"shape {P.shape}")
        P[0] = self.positions[0]
        h = self.knot_interval
        parts = [_increments(np.diff(P, axis=0) / h, self.max_acceleration * h)]
        if self.rotates:
            Y = np.array(self.yaw if yaw is None else yaw, dtype=np.float64).reshape(-1)
            if Y.shape != self.yaw.shape or not np.all(np.isfinite(Y)):
                raise ValueError(f"{self.name}: yaw must be {self.knot_count} finite angles [rad]")
            Y[0] = self.yaw[0]
            parts.append(_increments(np.diff(Y)[:, None] / h, self.max_yaw_acceleration * h))
        return np.concatenate([p.reshape(-1) for p in parts])

    def control_points(self, params) -> tuple[np.ndarray, np.ndarray | None]:
        """Control points (K, 3) [m] and yaws (K,) [rad] (None without yaw) of ``params`` (:attr:`n_params`
        numbers): knot 0 as given, then velocity points built from bounded increments, each projected into the
        limits, so every parameter vector gives a trajectory within them."""
        p = self._check_params(params)
        K, h = self.knot_count, self.knot_interval
        z = p[:3 * (K - 1)].reshape(K - 1, 3)
        V, _ = _bounded_velocities(z, self.max_speed, self.max_acceleration * h)
        P = self.positions[0] + h * np.concatenate([np.zeros((1, 3)), np.cumsum(V, axis=0)])
        yaw = None
        if self.rotates:
            W, _ = _bounded_velocities(p[3 * (K - 1):].reshape(K - 1, 1), self.max_yaw_rate,
                                       self.max_yaw_acceleration * h)
            yaw = self.yaw[0] + h * np.concatenate([[0.0], np.cumsum(W[:, 0])])
        return P, yaw

    def control_points_vjp(self, params, grad_points: np.ndarray, grad_yaw: np.ndarray | None) -> np.ndarray:
        """The gradient with respect to ``params`` of a loss whose gradients with respect to :meth:`control_points`'
        outputs are ``grad_points`` (K, 3) and ``grad_yaw`` (K,) (ignored without yaw)."""
        p = self._check_params(params)
        K, h = self.knot_count, self.knot_interval
        parts = [_bounded_velocities_vjp(p[:3 * (K - 1)].reshape(K - 1, 3), self.max_speed,
                                         self.max_acceleration * h, _cumsum_vjp(grad_points, h))]
        if self.rotates:
            g = np.zeros(K) if grad_yaw is None else np.asarray(grad_yaw, dtype=np.float64)
            parts.append(_bounded_velocities_vjp(p[3 * (K - 1):].reshape(K - 1, 1), self.max_yaw_rate,
                                                 self.max_yaw_acceleration * h, _cumsum_vjp(g[:, None], h)))
        return np.concatenate([q.reshape(-1) for q in parts])

    def velocity_points(self, points: np.ndarray) -> np.ndarray:
        """The velocity control points (K - 1, d) [per s] of control points (K, d): the speed is at most their
        largest norm (the convex hull of the derivative's B-spline)."""
        return np.diff(np.asarray(points, dtype=np.float64).reshape(self.knot_count, -1), axis=0) / self.knot_interval

    def acceleration_points(self, points: np.ndarray) -> np.ndarray:
        """The acceleration control points (K - 1, d) [per s^2] (the start from rest included): the acceleration is
        at most their largest norm."""
        V = self.velocity_points(points)
        return np.diff(np.concatenate([np.zeros((1, V.shape[1])), V]), axis=0) / self.knot_interval

    def _check_params(self, params) -> np.ndarray:
        p = np.asarray(params, dtype=np.float64).reshape(-1)
        if p.size != self.n_params or not np.all(np.isfinite(p)):
            raise ValueError(f"{self.name}: parameters must be {self.n_params} finite numbers, got {p.size}")
        return p

    def _check_limits(self) -> None:
        """ValueError where the scripted knots break a limit, naming the knot."""
        channels = [("speed", "acceleration", self.positions, self.max_speed, self.max_acceleration, "m/s")]
        if self.rotates:
            channels.append(("yaw rate", "yaw acceleration", self.yaw[:, None], self.max_yaw_rate,
                             self.max_yaw_acceleration, "rad/s"))
        for speed_name, accel_name, points, v_max, a_max, unit in channels:
            V = np.linalg.norm(self.velocity_points(points), axis=1)
            A = np.linalg.norm(self.acceleration_points(points), axis=1)
            for k in range(V.size):
                if V[k] > v_max * (1 + _TOL):
                    raise ValueError(f"{self.name}: knots {k} and {k + 1} make a {speed_name} of {V[k]:.4g} {unit}, "
                                     f"past max {v_max:g} (the trajectory is past its limits at the start)")
                if A[k] > a_max * (1 + _TOL):
                    where = "from rest to knot 1" if k == 0 else f"at knot {k}"
                    raise ValueError(f"{self.name}: the {accel_name} {where} is {A[k]:.4g} {unit}/s, past max "
                                     f"{a_max:g} (the trajectory is past its limits at the start)")

    # -- targets ---------------------------------------------------------------------------------------------------
    def frames(self, params, times) -> tuple[np.ndarray, np.ndarray]:
        """The frame's displacements c (len(times), 3) [m] and yaws (len(times),) [rad] at ``times`` [s]."""
        P, yaw = self.control_points(params)
        W = self.weights(times)
        return W @ P, (W @ yaw if yaw is not None else np.zeros(W.shape[0]))

    def targets(self, params, times, x0: np.ndarray) -> np.ndarray:
        """The held particles' targets (len(times), n, 3) [m] at ``times``, their initial positions ``x0`` (n, 3)."""
        c, yaw = self.frames(params, times)
        cg, yg = self.frames(params, [self.grasp])
        x0 = np.asarray(x0, dtype=np.float64)
        centre = x0.mean(axis=0)
        r = x0 - centre - cg[0]
        return centre + c[:, None, :] + _rotate(r[None, :, :], yaw - yg[0])

    def targets_vjp(self, params, times, x0: np.ndarray, grad: np.ndarray) -> np.ndarray:
        """The gradient with respect to ``params`` of a loss whose gradient with respect to :meth:`targets`'
        output is ``grad`` (len(times), n, 3)."""
        P, yaw = self.control_points(params)
        W, wg = self.weights(times), self.weights([self.grasp])[0]
        G = np.asarray(grad, dtype=np.float64)
        phi = (W @ yaw - wg @ yaw) if self.rotates else np.zeros(W.shape[0])
        x0 = np.asarray(x0, dtype=np.float64)
        r = x0 - x0.mean(axis=0) - wg @ P
        g_r = _rotate(G, -phi).sum(axis=0)  # sum_s R(phi_s)^T G[s, j]
        g_points = W.T @ G.sum(axis=1) - np.outer(wg, g_r.sum(axis=0))
        g_yaw = None
        if self.rotates:
            Rr = _rotate(r[None], phi)
            g_phi = np.sum(G[..., 1] * Rr[..., 0] - G[..., 0] * Rr[..., 1], axis=1)  # G . (e_z x R r)
            g_yaw = W.T @ g_phi - wg * g_phi.sum()
        return self.control_points_vjp(params, g_points, g_yaw)


def _rotate(r: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotate vectors r (S, n, 3) about +z by angle (S,)."""
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    out = np.empty(np.broadcast_shapes(r.shape, (angle.size, 1, 3)))
    out[..., 0] = c * r[..., 0] - s * r[..., 1]
    out[..., 1] = s * r[..., 0] + c * r[..., 1]
    out[..., 2] = r[..., 2]
    return out


def _ball(w: np.ndarray, radius: float) -> np.ndarray:
    """Project the rows of w into the ball of ``radius``."""
    norm = np.linalg.norm(w, axis=-1, keepdims=True)
    return w * np.minimum(1.0, radius / np.maximum(norm, 1e-300))


def _ball_vjp(w: np.ndarray, radius: float, g: np.ndarray) -> np.ndarray:
    norm = float(np.linalg.norm(w))
    if norm <= radius:
        return g
    u = w / norm
    return (radius / norm) * (g - u * float(u @ g))


def _bounded_velocities(z: np.ndarray, v_max: float, dv_max: float) -> tuple[np.ndarray, list]:
    """V_j = ball_vmax(V_{j-1} + dv_max ball_1(z_j)) from V_{-1} = 0: |V_j| <= v_max, |V_j - V_{j-1}| <= dv_max
    (a projection into a convex set containing V_{j-1} moves no point further from it)."""
    V = np.zeros_like(z)
    pre = []
    last = np.zeros(z.shape[1])
    for j in range(z.shape[0]):
        w = last + dv_max * _ball(z[j], 1.0)
        pre.append(w)
        last = _ball(w, v_max)
        V[j] = last
    return V, pre


def _bounded_velocities_vjp(z: np.ndarray, v_max: float, dv_max: float, gV: np.ndarray) -> np.ndarray:
    _, pre = _bounded_velocities(z, v_max, dv_max)
    gz = np.zeros_like(z)
    carry = np.zeros(z.shape[1])
    for j in reversed(range(z.shape[0])):
        gw = _ball_vjp(pre[j], v_max, gV[j] + carry)
        gz[j] = dv_max * _ball_vjp(z[j], 1.0, gw)
        carry = gw
    return gz


def _cumsum_vjp(grad_points: np.ndarray, h: float) -> np.ndarray:
    """dL/dV_j from dL/dP (P_{j+1} = P_j + h V_j, P_0 fixed): h times the sum of dL/dP_i over i > j."""
    g = np.asarray(grad_points, dtype=np.float64)
    return h * np.cumsum(g[::-1], axis=0)[::-1][1:]


def _increments(V: np.ndarray, dv_max: float) -> np.ndarray:
    """The parameters z of velocity points V within the limits (the inverse of :func:`_bounded_velocities`)."""
    return np.diff(np.concatenate([np.zeros((1, V.shape[1])), V]), axis=0) / dv_max


class GripperMotion:
    """Held particle ``index``'s scripted target offset from its initial position [m] (``Model.handle_motion``'s
    ``at(t)``), the gripper at its knots; ``x0``: the held particles' initial positions (n, 3)."""

    def __init__(self, gripper: Gripper, x0: np.ndarray, index: int):
        self.gripper, self.index = gripper, int(index)
        self.x0 = np.asarray(x0, dtype=np.float64)
        self._params = gripper.default_params()

    def at(self, t: float) -> np.ndarray:
        return self.gripper.targets(self._params, [t], self.x0)[0, self.index] - self.x0[self.index]
