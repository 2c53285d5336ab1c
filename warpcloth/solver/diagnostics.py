"""What the Simulator says when a step fails: the step, the particle and, where they explain it, the wind's stability
limit or the most elongated triangle."""

from __future__ import annotations

import math
import warnings

import numpy as np
import warp as wp

from warpcloth.errors import SimulationError
from warpcloth.model import Model, State

ELONGATED_ASPECT_RATIO = 100.0
"""Rest aspect ratio (longest edge^2 / (2 area)) from which failure messages name the most elongated triangle."""


class StepDiagnostics:

    def __init__(self, model: Model, dt: float):
        self.model = model
        self.dt = float(dt)
        self._elongated: tuple[int, float, int] | None = None  # (triangle, aspect ratio, count): mesh_hint

    def divergence_error(self, state: State, particle: int, t: float, step: int, max_speed: float) -> SimulationError:
        """The error of a step whose result ``state`` (step number ``step``, time ``t``) the divergence guard
        flagged at ``particle``; ``state`` may be None where the check came after the step's result was gone."""
        hints = self.wind_hint() + self.mesh_hint()
        when = f"step {step}" + (f" (t = {t:.4g} s)" if t is not None else "")
        if state is None:
            return SimulationError(
                f"simulation diverged at {when}: {self.model.particle_name(particle)} became non-finite or faster "
                f"than SolverOptions.max_speed = {max_speed:g} m/s; lower dt, raise damping, or check the material "
                "and forces (check every step, SolverOptions.sync_every=1, or pass the trajectory to "
                "Simulator.check, to see its position and velocity)" + hints, worlds=[self.model.world_of(particle)])
        x = state.particle_x.numpy()[particle]
        v = state.particle_v.numpy()[particle]
        speed = float(np.linalg.norm(v))
        if np.all(np.isfinite(x)) and np.all(np.isfinite(v)):
            return SimulationError(
                f"simulation diverged at {when}: {self.model.particle_name(particle)} moves at "
                f"{speed:.4g} m/s, "
                f"over SolverOptions.max_speed = {max_speed:g} m/s (x = {x.tolist()}); lower dt, raise damping, or "
                "check the material and forces; if the motion really is this fast (a long free fall), raise "
                "max_speed" + hints, worlds=[self.model.world_of(particle)])
        return SimulationError(
            f"simulation diverged at {when}: {self.model.particle_name(particle)} has "
            f"x = {x.tolist()}, "
            f"v = {v.tolist()}; lower dt, raise damping, or check the material and forces" + hints,
            worlds=[self.model.world_of(particle)])

    def non_finite_cause(self, state_in: State, values: wp.array, rhs: wp.array) -> str | None:
        """What made a solve's residual non-finite, naming the particle: a non-finite or overflowing input state,
        or non-finite forces or stiffness blocks (a material too stiff for the precision); None if none of those."""
        model = self.model
        for field, what in (("particle_x", "position"), ("particle_v", "velocity")):
            a = getattr(state_in, field).numpy()
            bad = np.flatnonzero(~np.all(np.isfinite(a), axis=1))
            if bad.size:
                p = int(bad[0])
                return f"{model.particle_name(p)} enters the step with a non-finite {what} {a[p].tolist()}"
        b = rhs.numpy().reshape(model.particle_count, -1)
        blocks = values.numpy().reshape(len(values), -1)
        largest = float(np.abs(blocks).max()) if np.all(np.isfinite(blocks)) else math.inf
        overflow = math.sqrt(np.finfo(blocks.dtype).max)  # the CG's products p.Ap overflow above about this
        if np.all(np.isfinite(b)) and largest < overflow:
            return None
        x = state_in.particle_x.numpy()
        far = np.flatnonzero(np.abs(x).max(axis=1) > 1.0e6)
        if far.size:
            p = int(far[0])
            return (f"{model.particle_name(p)} is at {x[p].tolist()}, more than 1e6 m from the origin: its edge "
                    "vectors lose "
                    f"their precision or overflow in {model.scalar.__name__}")
        bad = np.flatnonzero(~np.all(np.isfinite(b), axis=1))
        stiffest = float(np.abs(model.material_stretching.numpy()).max())
        which = (f"the forces on {model.particle_name(int(bad[0]))} are not finite" if bad.size else
                 f"the implicit system's largest entry is {largest:.3g}")
        return (f"{which}: the material's stiffness (largest stretching entry {stiffest:.3g}) or the forces "
                f"overflow {model.scalar.__name__}")

    def warn_if_below_atol(self, step: int, cg_atol: float) -> None:
        """Warn (RuntimeWarning) when the weight's impulse over a step, dt |g| |m|, is within ten times ``cg_atol``:
        every solve then stops at once on that floor and the cloth never moves."""
        g = max(float(np.max(np.linalg.norm(self.model.gravity.numpy(), axis=1))), 1.0)
        impulse = self.dt * g * float(np.linalg.norm(self.model.particle_mass()))
        if impulse <= 10.0 * cg_atol:
            warnings.warn(
                f"step {step}: the solve stopped after 0 iterations on SolverOptions.cg_atol = {cg_atol:g}, and this "
                f"model is too light for that floor (its weight's impulse over a step is {impulse:.3g} N*s): its "
                "solves are skipped and the cloth does not move; lower cg_atol", RuntimeWarning, stacklevel=4)

    def wind_hint(self) -> str:
        """Why the explicit wind force may have diverged (else ""): dt beyond 2 (area density) / ((wind density) |u|)
        for the relative normal velocity u, or 2 (area density) / drag: it has no Jacobian in the system."""
        model = self.model
        if model.wind_velocity is None:
            return ""
        # the stiffest world's wind (worlds may differ)
        speed = float(np.max(np.linalg.norm(model.wind_velocity.numpy(), axis=1)))
        air, drag = float(np.max(model.wind_density.numpy())), float(np.max(model.wind_drag.numpy()))
        cloth = float(np.min(model.material_density.numpy() * model.material_thicken.numpy()))
        limits = {}
        if air * speed > 0.0:
            limits["2*(cloth density)/(wind density*|wind|)"] = 2.0 * cloth / (air * speed)
        if drag > 0.0:
            limits["2*(cloth density)/(wind drag)"] = 2.0 * cloth / drag
        if not limits or self.dt <= min(limits.values()):
            return ""
        formula, limit = min(limits.items(), key=lambda item: item[1])
        return (f"; the wind force is explicit: a {speed:.3g} m/s wind (density {air:g}, drag {drag:g}) on cloth of "
                f"{cloth:.3g} kg/m^2 is stable only for dt < {formula} = {limit:.3g} s: lower dt below that, or the "
                "wind speed")

    def mesh_hint(self) -> str:
        """Name the most elongated rest triangle when it reaches ELONGATED_ASPECT_RATIO (else "")."""
        model = self.model
        if self._elongated is None:  # computed on the first failure only
            dm = np.linalg.inv(model.tri_inv_dm.numpy().astype(np.float64))  # columns: material-space edges
            e1, e2 = dm[:, :, 0], dm[:, :, 1]
            longest = np.max([np.sum(e * e, axis=1) for e in (e1, e2, e2 - e1)], axis=0)
            aspect = longest / np.abs(np.linalg.det(dm))  # longest^2 / (2 area): 2 for half a square
            t = int(np.argmax(aspect))
            self._elongated = (t, float(aspect[t]), int(np.count_nonzero(aspect >= ELONGATED_ASPECT_RATIO)))
        t, ratio, count = self._elongated
        if ratio < ELONGATED_ASPECT_RATIO:
            return ""
        return (f"; triangle {t} {model.triangles_np[t].tolist()} is elongated (rest aspect ratio {ratio:.3g}; "
                f"{count} triangle(s) at or above {ELONGATED_ASPECT_RATIO:g}), which makes the system ill-conditioned: "
                "remesh it, or use dtype=wp.float64")
