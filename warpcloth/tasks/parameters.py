"""Free scene parameters of an estimation, by name: what a fit may fit beside the material (the wind, friction,
handle stiffness, the start's placement and velocity, obstacle placement), each read from and written into a
:class:`~warpcloth.tasks.estimation.TrajectoryFit`'s model, with the gradient of the fit's loss, and the bounded or
unbounded change of variables the optimiser works in (:class:`ParameterTransform`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

SCENE_PARAMETERS = {
    "wind": "the wind's velocity [m/s], (3,); linear, scale 1 m/s",
    "wind_density": "the wind pressure's air density [kg/m^3], (1,); log space",
    "wind_drag": "the wind's tangential drag coefficient [kg/(m^2 s)], (1,); log space (a scene's must be > 0)",
    "gravity": "the gravitational acceleration [m/s^2], (3,); linear, scale 1 m/s^2",
    "obstacle_friction": "the cloth-obstacle Coulomb friction coefficient [-], (1,); log space",
    "cloth_friction": "the cloth-cloth Coulomb friction coefficient [-], (1,); log space (self-collision scenes)",
    "contact_stiffness": "the contact repulsion stiffness per m^2 of rest area [N/m^3], (1,); log space",
    "handle_stiffness": "each soft handle's stiffness [N/m], (handle_count,); log space",
    "damping_mass": "the Rayleigh mass-proportional damping alpha [1/s], (1,); log space (a scene's [damping] "
                    "mass must be > 0)",
    "damping_stiffness": "the Rayleigh stiffness-proportional damping beta [s], (1,); log space (a scene's "
                         "[damping] stiffness must be > 0)",
    "start_placement": "a rigid move of the start positions: a rotation vector [rad] about the cloth's centre (the "
                       "mean start position) then a translation [m], (6,); linear, scales 0.1 rad and 0.01 m; the "
                       "velocities, handle and pin targets stay",
    "start_deformation": "a smooth deformation of the start positions: coefficients [m^2] of the START_MODES "
                         "smoothest displacements of the start shape (registration.SmoothDeformation, the held "
                         "particles fixed; fewer on a cloth of fewer free particles), before start_placement, "
                         "(START_MODES * 3,); linear, scale 1 cm of RMS displacement; the velocities, handle and pin "
                         "targets stay",
    "start_deformation_rate": "a smooth start velocity: coefficients [m^2/s] of the same displacements as "
                              "start_deformation, added to the start velocities, (START_MODES * 3,); linear, scale "
                              "0.1 m/s of RMS velocity",
    "start_velocity": "a velocity [m/s] added to every particle's start velocity, (3,); linear, scale 0.1 m/s",
    "start_velocities": "a velocity [m/s] added to each particle's start velocity, (particle_count * 3,); linear, "
                        "scale 0.1 m/s",
    "obstacle_placement": "each obstacle's rigid move: a rotation vector [rad] about its body origin then a "
                          "translation [m], (obstacle_count * 6,); linear, scales 0.1 rad and 0.01 m",
}
"""The scene parameters an estimation can free (beside the material's ``density``, ``stretching``, ``bending``):
name to what it is, its units and shape, and how it is fitted."""

NOT_OFFERED = {
    "damping": "the Rayleigh damping is two parameters: name damping_mass (alpha) or damping_stiffness (beta)",
}
"""Names refused with the reason and what to name instead."""

_ROTATION_SCALE = 0.1  # [rad]
_TRANSLATION_SCALE = 0.01  # [m]
_VELOCITY_SCALE = 0.1  # [m/s]
_SHAPE_SCALE = 0.01  # [m]
START_MODES = 16
"""How many smooth displacements ``start_deformation`` and ``start_deformation_rate`` take."""


# -- rotations (analytic, so that a complex step differentiates them) ------------------------------------------------
def _sin_terms(t2):
    # sin(t)/t and (1 - cos t)/t^2 as functions of t^2, analytic (complex steps at t = 0 included)
    if abs(t2) < 1e-12:
        return 1.0 - t2 / 6.0 + t2 * t2 / 120.0, 0.5 - t2 / 24.0 + t2 * t2 / 720.0
    t = np.sqrt(t2)
    return np.sin(t) / t, (1.0 - np.cos(t)) / t2


def rotation_matrix(r: np.ndarray) -> np.ndarray:
    """The rotation of rotation vector ``r`` [rad] (axis times angle), (3, 3)."""
    r = np.asarray(r)
    a, b = _sin_terms(r @ r)
    k = np.array([[0.0 * r[0], -r[2], r[1]], [r[2], 0.0 * r[0], -r[0]], [-r[1], r[0], 0.0 * r[0]]])
    return np.eye(3) + a * k + b * (k @ k)


def rotation_quaternion(r: np.ndarray) -> np.ndarray:
    """The unit quaternion (x, y, z, w) of rotation vector ``r`` [rad]."""
    r = np.asarray(r)
    t2 = r @ r
    if abs(t2) < 1e-12:
        s, c = 0.5 - t2 / 48.0 + t2 * t2 / 3840.0, 1.0 - t2 / 8.0 + t2 * t2 / 384.0
    else:
        t = np.sqrt(t2)
        s, c = np.sin(0.5 * t) / t, np.cos(0.5 * t)
    return np.concatenate([r * s, [c]])


def _quat_mul(p, q):
    pv, pw, qv, qw = p[:3], p[3], q[:3], q[3]
    return np.concatenate([pw * qv + qw * pv + np.cross(pv, qv), [pw * qw - pv @ qv]])


def _jacobian(f, r: np.ndarray) -> np.ndarray:
    # d f / d r by complex steps: exact to rounding for the analytic maps above
    h = 1e-30
    cols = []
    for k in range(3):
        z = np.asarray(r, dtype=np.complex128).copy()
        z[k] += 1j * h
        cols.append(np.imag(f(z)) / h)
    return np.stack(cols, axis=-1)


# -- the change of variables -----------------------------------------------------------------------------------------
class ParameterTransform:
    """A parameter's values ``raw`` (flat) as a function of the optimiser's ``t`` (t = 0: ``start``), with its
    derivative. Positive parameters are fitted in log space. ``scale``: the change of ``raw`` (linear) or of
    ``log raw`` (positive) per unit of ``t`` at the start. ``bounds`` (low, high), each a number or one per entry,
    None or +-inf for none: ``t`` maps onto the open interval (a logistic map where both are finite, an exponential
    where one is), so no step leaves it and nothing is clamped. ValueError naming ``name`` (and the entry) for a
    start outside the bounds, a positive parameter whose start is not > 0, or a scale that is not > 0."""

    def __init__(self, name: str, start: np.ndarray, *, positive: bool, scale, bounds=None):
        start = np.asarray(start, dtype=np.float64).ravel()
        n = start.size
        self.name, self.positive, self.start = name, positive, start

        def per_entry(value, what):
            try:
                out = np.broadcast_to(np.asarray(value, dtype=np.float64).ravel()
                                      if np.ndim(value) else np.float64(value), (n,)).copy()
            except (ValueError, TypeError):
                raise ValueError(f"free parameter {name!r}: {what} must be a number or {n} numbers, got "
                                 f"{value!r}") from None
            return out

        self.scale = per_entry(scale, "scale")
        if not np.all(np.isfinite(self.scale) & (self.scale > 0.0)):
            raise ValueError(f"free parameter {name!r}: scale must be finite and > 0, got {self.scale.tolist()}")
        if positive and np.any(start <= 0.0):
            k = int(np.flatnonzero(start <= 0.0)[0])
            raise ValueError(f"free parameter {name!r}: entry {k} starts at {start[k]:g}; it is fitted in log space "
                             "and must start > 0")
        if bounds is None:
            low, high = np.full(n, -np.inf), np.full(n, np.inf)
        else:
            if not isinstance(bounds, (Sequence, np.ndarray)) or len(bounds) != 2:
                raise ValueError(f"free parameter {name!r}: bounds must be [low, high], got {bounds!r}")
            low = per_entry(-np.inf if bounds[0] is None else bounds[0], "the low bound")
            high = per_entry(np.inf if bounds[1] is None else bounds[1], "the high bound")
        if np.any(np.isnan(low) | np.isnan(high)) or np.any(low >= high):
            raise ValueError(f"free parameter {name!r}: bounds need low < high, got {low.tolist()}, {high.tolist()}")
        outside = np.flatnonzero((start <= low) | (start >= high))
        if outside.size:
            k = int(outside[0])
            raise ValueError(f"free parameter {name!r}: entry {k} starts at {start[k]:g}, not inside its bounds "
                             f"({low[k]:g}, {high[k]:g})")
        if positive and np.any(high <= 0.0):
            raise ValueError(f"free parameter {name!r}: a positive parameter's high bound must be > 0")
        self.low, self.high = low, high
        with np.errstate(divide="ignore"):
            y0 = np.log(start) if positive else start.copy()
            a = np.where(low > 0.0, np.log(np.where(low > 0.0, low, 1.0)), -np.inf) if positive else low
            b = np.log(high) if positive else high
        self._y0, self._a, self._b = y0, a, b
        self._both = np.isfinite(a) & np.isfinite(b)
        self._low_only = np.isfinite(a) & ~np.isfinite(b)
        self._high_only = ~np.isfinite(a) & np.isfinite(b)
        width = np.where(self._both, b - a, 1.0)
        u0 = np.where(self._both, (y0 - np.where(self._both, a, 0.0)) / width, 0.5)
        self._s0 = np.log(u0 / (1.0 - u0))
        k = self.scale
        self._c = np.where(self._both, k / (width * u0 * (1.0 - u0)),
                           np.where(self._low_only, k / np.where(self._low_only, y0 - a, 1.0),
                                    np.where(self._high_only, k / np.where(self._high_only, b - y0, 1.0), k)))

    @property
    def size(self) -> int:
        return self.start.size

    def _y(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=np.float64)
        if t.shape != (self.size,):
            raise ValueError(f"free parameter {self.name!r}: expected {self.size} values, got shape {t.shape}")
        c, a, b = self._c, self._a, self._b
        with np.errstate(over="ignore", invalid="ignore"):
            sig = 1.0 / (1.0 + np.exp(-(self._s0 + c * t)))
            e_low = np.exp(c * t)
            e_high = np.exp(-c * t)
            y = np.where(self._both, a + (b - a) * sig,
                         np.where(self._low_only, a + (self._y0 - a) * e_low,
                                  np.where(self._high_only, b - (b - self._y0) * e_high, self._y0 + c * t)))
            dy = np.where(self._both, (b - a) * sig * (1.0 - sig) * c,
                          np.where(self._low_only, (self._y0 - a) * e_low * c,
                                   np.where(self._high_only, (b - self._y0) * e_high * c, c)))
        return y, dy

    def decode(self, t: np.ndarray) -> np.ndarray:
        """The values at ``t``, flat."""
        y, _ = self._y(t)
        return np.exp(y) if self.positive else y

    def chain(self, t: np.ndarray, g_raw: np.ndarray) -> np.ndarray:
        """d loss / d t from d loss / d values."""
        y, dy = self._y(t)
        g = np.asarray(g_raw, dtype=np.float64).ravel()
        return g * dy * (np.exp(y) if self.positive else 1.0)


# -- the parameters --------------------------------------------------------------------------------------------------
class SceneParameter:
    """One free scene parameter bound to a fit: :meth:`read` its values (flat, float64), :meth:`write` them into
    the fit's model or start, :meth:`grad` d loss / d values of the fit's last evaluation with a gradient, and
    :meth:`zero_grad`. ``positive``: fitted in log space; ``scale``: the default scale (``ParameterTransform``)."""

    name = ""
    positive = False
    scale: float | np.ndarray = 1.0

    def __init__(self, fit):
        self.fit = fit
        self.model = fit.model

    def read(self) -> np.ndarray:
        raise NotImplementedError

    def write(self, values: np.ndarray) -> None:
        raise NotImplementedError

    def grad(self) -> np.ndarray:
        raise NotImplementedError

    def zero_grad(self) -> None:
        raise NotImplementedError


def _missing(name: str, what: str) -> ValueError:
    return ValueError(f"free parameter {name!r}: the scene has {what}")


class _ArrayEntries(SceneParameter):
    # entries ``index`` (of the flattened array, None: all) of a model array that takes gradients

    def __init__(self, fit, name, attr, *, positive, scale, index=None, absent="no such input"):
        super().__init__(fit)
        self.name, self.positive, self.scale, self.index = name, positive, scale, index
        self.array = getattr(self.model, attr)
        if self.array is None:
            raise _missing(name, absent)
        if self.array.grad is None:
            raise ValueError(f"free parameter {name!r}: model.{attr} takes no gradient (finalize the model with "
                             "requires_grad=True)")

    def _flat(self, a: np.ndarray) -> np.ndarray:
        flat = np.asarray(a, dtype=np.float64).reshape(-1)
        return flat.copy() if self.index is None else flat[self.index].copy()

    def read(self) -> np.ndarray:
        return self._flat(self.array.numpy())

    def write(self, values: np.ndarray) -> None:
        full = self.array.numpy().copy()
        flat = full.reshape(-1)
        if self.index is None:
            flat[:] = values
        else:
            flat[self.index] = values
        self.array.assign(full)

    def grad(self) -> np.ndarray:
        return self._flat(self.array.grad.numpy())

    def zero_grad(self) -> None:
        self.array.grad.zero_()


class _Start:
    # the start state the start parameters edit together: base positions and velocities, and each parameter's part

    def __init__(self, fit):
        model = fit.model
        self.fit, self.model = fit, model
        self.x_base = model.particle_x0.numpy().astype(np.float64)
        self.v_base = model.particle_v0.numpy().astype(np.float64)
        self.centre = self.x_base.mean(axis=0)
        self.placement = np.zeros(6)
        self.velocity = np.zeros(3)
        self.velocities = np.zeros_like(self.v_base)
        self._modes = None
        held = [a.numpy() for a in (model.handle_particle, model.pin_particle) if a is not None]
        self.held = np.unique(np.concatenate(held)) if held else np.zeros(0, dtype=np.int64)
        count = min(START_MODES, len(self.x_base) - len(self.held))  # a cloth of few particles: fewer modes
        self.shape = np.zeros((count, 3))
        self.rate = np.zeros((count, 3))

    @property
    def modes(self):
        """The start shape's smooth displacements (registration.SmoothDeformation), the held particles fixed."""
        if self._modes is None:
            from warpcloth.registration import SmoothDeformation

            self._modes = SmoothDeformation(self.x_base, self.model.triangles_np, len(self.shape), fixed=self.held)
        return self._modes

    def relative(self) -> np.ndarray:
        # the deformed start about the centre, before the rigid placement
        x = self.x_base if self._modes is None else self.x_base + self._modes.basis @ self.shape
        return x - self.centre

    def write(self) -> None:
        r, t = self.placement[:3], self.placement[3:]
        x = self.relative() @ rotation_matrix(r).T + self.centre + t
        self.model.particle_x0.assign(x)
        v = self.v_base + self.velocity + self.velocities
        if self._modes is not None:
            v = v + self._modes.basis @ self.rate
        self.model.particle_v0.assign(v)

    def grads(self) -> tuple[np.ndarray, np.ndarray]:
        state = self.fit.start_state
        if state is None:
            raise ValueError("the start's gradient is read after an evaluation with a gradient")
        return (state.particle_x.grad.numpy().astype(np.float64), state.particle_v.grad.numpy().astype(np.float64))

    def zero(self) -> None:
        state = self.fit.start_state
        for a in (() if state is None else (state.particle_x, state.particle_v)) + (self.model.particle_x0,
                                                                                     self.model.particle_v0):
            if a.grad is not None:
                a.grad.zero_()


class _StartPart(SceneParameter):
    # one part of the shared _Start (its attribute ``attr``), read flat and written back in that part's shape

    attr = ""

    def __init__(self, fit, start: _Start):
        super().__init__(fit)
        self.start = start

    def read(self):
        return getattr(self.start, self.attr).ravel().copy()

    def write(self, values):
        shape = getattr(self.start, self.attr).shape
        setattr(self.start, self.attr, np.asarray(values, dtype=np.float64).reshape(shape).copy())
        self.start.write()

    def zero_grad(self):
        self.start.zero()


class _StartPlacement(_StartPart):
    name, attr = "start_placement", "placement"
    scale = np.array([_ROTATION_SCALE] * 3 + [_TRANSLATION_SCALE] * 3)

    def grad(self):
        gx, _ = self.start.grads()
        s = self.start
        rel = s.relative()
        jac = _jacobian(rotation_matrix, s.placement[:3])  # (3, 3, 3): d R / d r_k
        g_r = [float(np.sum(gx * (rel @ jac[:, :, k].T))) for k in range(3)]
        return np.concatenate([g_r, gx.sum(axis=0)])


class _StartVelocity(_StartPart):
    name, attr = "start_velocity", "velocity"
    scale = _VELOCITY_SCALE

    def grad(self):
        return self.start.grads()[1].sum(axis=0)


class _StartVelocities(_StartPart):
    name, attr = "start_velocities", "velocities"
    scale = _VELOCITY_SCALE

    def grad(self):
        return self.start.grads()[1].ravel()


class _StartDeformation(_StartPart):
    name, attr = "start_deformation", "shape"

    def __init__(self, fit, start: _Start):
        super().__init__(fit, start)
        self.scale = _SHAPE_SCALE * np.sqrt(start.modes.mass.sum())  # mass-orthonormal modes: RMS over the area

    def grad(self):
        gx, _ = self.start.grads()
        return (self.start.modes.basis.T @ gx @ rotation_matrix(self.start.placement[:3])).ravel()


class _StartDeformationRate(_StartPart):
    name, attr = "start_deformation_rate", "rate"

    def __init__(self, fit, start: _Start):
        super().__init__(fit, start)
        self.scale = _VELOCITY_SCALE * np.sqrt(start.modes.mass.sum())

    def grad(self):
        return (self.start.modes.basis.T @ self.start.grads()[1]).ravel()


class _ObstaclePlacement(SceneParameter):
    name = "obstacle_placement"

    def __init__(self, fit):
        super().__init__(fit)
        model = self.model
        if model.obstacle_count == 0:
            raise _missing(self.name, "no obstacle")
        self.base = np.asarray(model.obstacle_rest_transform, dtype=np.float64).copy()  # (k, 7): p, q (x, y, z, w)
        self.values = np.zeros((model.obstacle_count, 6))
        self.scale = np.tile([_ROTATION_SCALE] * 3 + [_TRANSLATION_SCALE] * 3, model.obstacle_count)

    def _transforms(self, values) -> np.ndarray:
        out = self.base.copy()
        for k, (r, t) in enumerate(zip(values[:, :3], values[:, 3:])):
            out[k, :3] = self.base[k, :3] + t
            out[k, 3:] = _quat_mul(rotation_quaternion(r), self.base[k, 3:])
        return out

    def read(self):
        return self.values.ravel().copy()

    def write(self, values):
        self.values = np.asarray(values, dtype=np.float64).reshape(-1, 6).copy()
        self.fit.control.obstacle_transform.assign(self._transforms(self.values))

    def grad(self):
        g = self.fit.control.obstacle_transform.grad.numpy().astype(np.float64).reshape(-1, 7)
        out = np.zeros_like(self.values)
        for k in range(len(out)):
            jac = _jacobian(lambda r, k=k: _quat_mul(rotation_quaternion(r), self.base[k, 3:]), self.values[k, :3])
            out[k, :3] = g[k, 3:] @ jac
            out[k, 3:] = g[k, :3]
        return out.ravel()

    def zero_grad(self):
        self.fit.control.obstacle_transform.grad.zero_()


def _make(fit, name: str, start: _Start) -> SceneParameter:
    model = fit.model
    if name == "wind":
        return _ArrayEntries(fit, name, "wind_velocity", positive=False, scale=1.0, absent="no wind ([wind])")
    if name == "wind_density":
        return _ArrayEntries(fit, name, "wind_density", positive=True, scale=1.0, absent="no wind ([wind])")
    if name == "wind_drag":
        return _ArrayEntries(fit, name, "wind_drag", positive=True, scale=1.0, absent="no wind ([wind])")
    if name == "gravity":
        return _ArrayEntries(fit, name, "gravity", positive=False, scale=1.0)
    if name in ("obstacle_friction", "cloth_friction", "contact_stiffness"):
        if model.collision is None:
            raise _missing(name, "no collisions (no obstacle, no self-collision)")
        if name == "obstacle_friction" and model.obstacle_count == 0:
            raise _missing(name, "no obstacle")
        if name == "cloth_friction" and not model.collision.self_collision:
            raise _missing(name, "no self-collision")
        if name != "contact_stiffness" and float(model.contact_repulsion_stiffness.numpy()[0]) == 0.0:
            raise _missing(name, "repulsion stiffness 0, and friction acts through the repulsion")
        if name == "contact_stiffness":
            return _ArrayEntries(fit, name, "contact_repulsion_stiffness", positive=True, scale=1.0)
        return _ArrayEntries(fit, name, "contact_friction", positive=True, scale=1.0,
                             index=[1] if name == "obstacle_friction" else [0])
    if name in ("damping_mass", "damping_stiffness"):
        return _ArrayEntries(fit, name, name, positive=True, scale=1.0)
    if name == "handle_stiffness":
        if model.handle_count == 0:
            raise _missing(name, "no soft handle")
        return _ArrayEntries(fit, name, "handle_stiffness", positive=True, scale=1.0)
    if name == "start_placement":
        return _StartPlacement(fit, start)
    if name == "start_velocity":
        return _StartVelocity(fit, start)
    if name == "start_deformation":
        return _StartDeformation(fit, start)
    if name == "start_deformation_rate":
        return _StartDeformationRate(fit, start)
    if name == "start_velocities":
        return _StartVelocities(fit, start)
    if name == "obstacle_placement":
        return _ObstaclePlacement(fit)
    raise AssertionError(name)


def check_names(names: Sequence[str], material_parts: Sequence[str], where: str = "free") -> None:
    """ValueError naming the first entry of ``names`` that is neither a material part nor a scene parameter (with
    the reason for one :data:`NOT_OFFERED`), or that repeats."""
    seen = set()
    for k, name in enumerate(names):
        if name in NOT_OFFERED:
            raise ValueError(f"{where}[{k}]: {name!r} names no one parameter: {NOT_OFFERED[name]}")
        if name not in material_parts and name not in SCENE_PARAMETERS:
            raise ValueError(f"{where}[{k}]: unknown free parameter {name!r}; choose from "
                             f"{', '.join(list(material_parts) + list(SCENE_PARAMETERS))}")
        if name in seen:
            raise ValueError(f"{where}[{k}]: names {name!r} a second time")
        seen.add(name)


def check_options(names: Sequence[str], options: Mapping | None, what: str) -> dict:
    """``options`` (bounds or scales by parameter name) checked against the free ``names``: ValueError naming a key
    that is no free scene parameter."""
    options = dict(options or {})
    for key in options:
        if key not in names or key not in SCENE_PARAMETERS:
            raise ValueError(f"{what}: {key!r} is not a free scene parameter (free: {', '.join(names)}); "
                             f"{what} apply to the scene parameters of {', '.join(SCENE_PARAMETERS)}")
    return options


def bind_parameters(fit, names: Sequence[str]) -> list[SceneParameter]:
    """The scene parameters ``names`` (of :data:`SCENE_PARAMETERS`) of ``fit`` (a one-world TrajectoryFit), in order;
    ValueError naming one the scene does not have."""
    start = _Start(fit)
    return [_make(fit, name, start) for name in names]


__all__ = ["SCENE_PARAMETERS", "NOT_OFFERED", "START_MODES", "ParameterTransform", "SceneParameter", "bind_parameters",
           "check_names", "check_options", "rotation_matrix", "rotation_quaternion"]
