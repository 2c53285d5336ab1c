"""Optimisers of a NumPy vector for losses from simulations, ``f(theta) -> (loss, gradient)``, counting calls."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

Objective = Callable[[np.ndarray], tuple[float, np.ndarray]]


class FitSummary:
    """What a fit's ``losses`` say (every evaluation's, in order; infinite for a rejected trial). Where ``horizons``
    lists each evaluation's, only the longest horizon's losses compare (shorter ones take fewer frames)."""

    def _compared(self) -> list[int]:
        horizons = getattr(self, "horizons", None)
        if horizons and len(horizons) == len(self.losses):
            return [k for k, h in enumerate(horizons) if h == max(horizons)]
        return list(range(len(self.losses)))

    @property
    def evaluations(self) -> int:
        return len(self.losses)

    @property
    def first_loss(self) -> float:
        """The first evaluation's loss (NaN before any)."""
        return self.losses[0] if self.losses else math.nan

    @property
    def best_evaluation(self) -> int:
        """The 1-based number of the evaluation of :attr:`best_loss` (the first of equals; 0 before any)."""
        compared = self._compared()
        return 1 + min(compared, key=lambda k: self.losses[k]) if compared else 0

    @property
    def best_loss(self) -> float:
        """The least loss (of the longest horizon's evaluations; NaN before any)."""
        return self.losses[self.best_evaluation - 1] if self.losses else math.nan

    def summary(self) -> str:
        """One line, such as ``"best loss 3.12e-05 at evaluation 37 of 60 (first 7.24e-04)"``."""
        if not self.losses:
            return "no evaluations"
        k = self.best_evaluation
        horizons = getattr(self, "horizons", None)
        shorter = (f", over {horizons[0]} of {horizons[k - 1]} steps"
                   if horizons and len(horizons) == len(self.losses) and horizons[0] != horizons[k - 1] else "")
        return (f"best loss {self.best_loss:.2e} at evaluation {k} of {self.evaluations} "
                f"(first {self.first_loss:.2e}{shorter})")


def adam(f: Objective, theta: np.ndarray, *, iters: int, lr: float = 0.05, betas=(0.9, 0.99),
         callback=None) -> np.ndarray:
    """Adam (Kingma and Ba 2015) on theta; keeps the best iterate (the loss is noisy near convergence)."""
    m = np.zeros_like(theta)
    v = np.zeros_like(theta)
    best = (math.inf, theta)
    for k in range(1, iters + 1):
        loss, g = f(theta)  # an infinite loss (a diverged trial) comes with a zero gradient: momentum carries on
        if loss < best[0]:
            best = (loss, theta.copy())
        if callback:
            callback(k, loss, theta)
        m = betas[0] * m + (1 - betas[0]) * g
        v = betas[1] * v + (1 - betas[1]) * g * g
        theta = theta - lr * (m / (1 - betas[0] ** k)) / (np.sqrt(v / (1 - betas[1] ** k)) + 1e-12)
    return best[1]


def check_backtracks(backtracks) -> None:
    """ValueError unless ``backtracks`` is None or an integer >= 1 (:func:`lbfgs`'s)."""
    if backtracks is not None and (isinstance(backtracks, bool) or not isinstance(backtracks, (int, np.integer))
                                   or backtracks < 1):
        raise ValueError(f"backtracks must be None or an integer >= 1, got {backtracks!r}")


def lbfgs(f: Objective, theta: np.ndarray, *, iters: int, memory: int = 10, max_step: float = 0.5,
          callback=None, first: tuple[float, np.ndarray] | None = None, backtracks: int | None = None) -> np.ndarray:
    """L-BFGS (Nocedal and Wright, alg. 7.4), its line search accepting any decrease, its first step sized for a loss
    whose minimum is near 0; ``iters`` counts evaluations, ``first`` (loss and gradient at theta, if known) among them;
    ``max_step`` bounds a step's change of any entry. With ``backtracks``, a line search that shrinks its step that
    many times without a decrease starts again from steepest descent, and one from steepest descent that fails so
    returns at once: no step along the gradient lowers the loss (the evaluations left are not spent). Without, the
    line search shrinks its step until a decrease or the end of ``iters``."""
    check_backtracks(backtracks)
    loss, g = f(theta) if first is None else first
    evals = 1
    if callback:
        callback(evals, loss, theta)
    s_hist: list[np.ndarray] = []
    y_hist: list[np.ndarray] = []
    while evals < iters:
        q = g.copy()
        alphas = []
        for s, y in zip(reversed(s_hist), reversed(y_hist)):
            a = s @ q / (y @ s)
            alphas.append(a)
            q -= a * y
        if s_hist:
            q *= (s_hist[-1] @ y_hist[-1]) / (y_hist[-1] @ y_hist[-1])
        else:  # Polyak's step for a loss whose minimum is about 0: the first step's length is then scale-free
            q *= loss / max(g @ g, 1e-300)
        for (s, y), a in zip(zip(s_hist, y_hist), reversed(alphas)):
            q += s * (a - (y @ q) / (y @ s))
        d = -q
        if g @ d >= 0:  # not a descent direction: restart from steepest descent
            s_hist.clear(), y_hist.clear()
            d = -g * loss / max(g @ g, 1e-300)
        step = min(1.0, max_step / max(np.abs(d).max(), 1e-30))
        shrinks = 0
        while evals < iters:
            new_theta = theta + step * d
            new_loss, new_g = f(new_theta)
            evals += 1
            if callback:
                callback(evals, new_loss, new_theta)
            if new_loss < loss:  # any decrease: contacts make the gradient a poor predictor of the decrease
                break
            step *= 0.3
            shrinks += 1
            if backtracks is not None and shrinks >= backtracks:
                break
        else:
            break
        if not new_loss < loss:  # the line search gave up
            if not s_hist:
                return theta
            s_hist.clear(), y_hist.clear()
            continue
        s, y = new_theta - theta, new_g - g
        if s @ y > 1e-12 * (s @ s):
            s_hist.append(s), y_hist.append(y)
            if len(s_hist) > memory:
                s_hist.pop(0), y_hist.pop(0)
        theta, loss, g = new_theta, new_loss, new_g
    return theta


@dataclass
class Smoothed:
    """:func:`smoothed_gradient`'s estimates at a point: ``loss``, the copies' mean, and ``grad``, flat, from the
    ``samples`` copies whose simulation ran (``failed`` raised and are left out)."""

    loss: float
    grad: np.ndarray
    samples: int
    failed: int


def smoothed_gradient(evaluate_many, params, *, scale: float, samples: int, rng: np.random.Generator,
                      zeroth_order: bool = False) -> Smoothed:
    """The gradient of L_s(p) = E[L(p + scale * eps)], eps ~ N(0, I), from ``samples`` copies of ``params`` in
    antithetic pairs, one batch of ``evaluate_many`` (as ``ControlTask.evaluate_many``). First order (default): the
    mean of the copies' gradients, blind to L's jumps. Zeroth order: the mean over pairs of (L(p + s eps) -
    L(p - s eps)) eps / (2 s), unbiased where L jumps too (Nesterov and Spokoiny 2017). ValueError for an odd
    ``samples`` or a ``scale`` not finite and positive."""
    if not (isinstance(samples, int) and samples >= 2 and samples % 2 == 0):
        raise ValueError(f"samples must be an even integer >= 2 (antithetic pairs), got {samples!r}")
    if not (np.isfinite(scale) and scale > 0.0):
        raise ValueError(f"scale must be finite and > 0, got {scale!r}")
    p = np.asarray(params, dtype=np.float64).reshape(-1)
    half = samples // 2
    eps = rng.standard_normal((half, p.size))
    eps = np.concatenate([eps, -eps])
    results = evaluate_many([(p + scale * e, None) for e in eps])
    ok = np.array([not isinstance(r, Exception) for r in results])
    if not ok.any():
        raise results[0]
    losses = np.array([r.loss if good else np.nan for r, good in zip(results, ok)])
    if zeroth_order:
        pairs = ok[:half] & ok[half:]
        if not pairs.any():
            raise next(r for r in results if isinstance(r, Exception))
        differences = (losses[:half] - losses[half:])[pairs] / (2.0 * scale)
        grad = (differences[:, None] * eps[:half][pairs]).mean(axis=0)
    else:
        grad = np.mean([r.grad for r, good in zip(results, ok) if good], axis=0)
    return Smoothed(loss=float(np.nanmean(losses)), grad=grad, samples=int(ok.sum()), failed=int((~ok).sum()))


SMOOTHED_COPIES = 8
"""The smoothed optimiser's perturbed copies a step (``SearchSpec.population``): four antithetic pairs."""
MULTISTART_POPULATION = 8
"""The multistart's default number of starts (``SearchSpec.population``)."""


def smoothed_steps(budget: int, refine: int, copies: int, *, unit: str, local: str) -> int:
    """The Adam steps of :func:`smoothed_descent` that ``budget`` simulations make, ``refine`` of them left to the
    ``local`` optimiser, ``copies`` a step; ValueError for odd ``copies`` or a budget that makes no step."""
    if copies % 2:
        raise ValueError(f"smoothed: search.population must be even (antithetic pairs), got {copies}")
    steps = (budget - refine) // copies
    if not steps:
        raise ValueError(f"smoothed: {budget} {unit}, {refine} of them left to {local}, make no step of {copies} "
                         "copies; raise iters or lower search.population/refine")
    return steps


def smoothed_descent(evaluate_many, x0: np.ndarray, *, sigma: float, step: float, copies: int, steps: int,
                     rng: np.random.Generator, failures: tuple[type[Exception], ...] = ()) -> np.ndarray:
    """Adam's best iterate on the Gaussian-smoothed loss from ``x0``: ``steps`` steps of length ``step``, each gradient
    from ``copies`` copies of spread ``sigma`` (:func:`smoothed_gradient`). A step whose every copy raised one of
    ``failures`` has an infinite loss, and Adam's momentum carries on."""

    def smoothed(theta: np.ndarray) -> tuple[float, np.ndarray]:
        try:
            s = smoothed_gradient(evaluate_many, theta, scale=sigma, samples=copies, rng=rng)
        except failures:
            return math.inf, np.zeros_like(theta)
        return s.loss, s.grad

    return adam(smoothed, np.asarray(x0, dtype=np.float64).reshape(-1), iters=steps, lr=step)


def cmaes(evaluate_population, x0: np.ndarray, *, sigma: float, generations: int, rng: np.random.Generator,
          popsize: int | None = None, callback=None) -> np.ndarray:
    """The best point CMA-ES (Hansen 2016, "The CMA Evolution Strategy: A Tutorial") evaluates from ``x0``, spread
    ``sigma``: ``evaluate_population(points) -> losses`` a generation at once (infinite for a failed simulation),
    ``popsize`` default 4 + floor(3 ln n). ValueError for a ``popsize`` under 2 or a ``sigma`` not finite and > 0."""
    x0 = np.asarray(x0, dtype=np.float64).reshape(-1)
    lam = popsize or 4 + int(3 * math.log(x0.size))
    return _cmaes_run(evaluate_population, x0, sigma, lam, generations, rng, None, callback, 0)[1]


def cmaes_restarts(evaluate_population, x0: np.ndarray, *, sigma: float, budget: int, rng: np.random.Generator,
                   popsize: int | None = None, growth: int = 2, stall: int = 8, callback=None) -> np.ndarray:
    """IPOP-CMA-ES (Auger and Hansen 2005): :func:`cmaes` from ``x0``, restarted from ``x0`` with ``growth`` times
    the population whenever a run's best loss has not dropped by 1e-3 of itself for ``stall`` generations, while
    ``budget`` evaluations last (a run stops where the next generation does not fit). Returns the best point of all
    runs. ValueError as :func:`cmaes`, or for ``growth`` < 1, ``stall`` < 1 or a budget under one population."""
    x0 = np.asarray(x0, dtype=np.float64).reshape(-1)
    lam = popsize or 4 + int(3 * math.log(x0.size))
    if growth < 1 or stall < 1:
        raise ValueError(f"cmaes_restarts needs growth >= 1 and stall >= 1, got {growth!r} and {stall!r}")
    if budget < lam:
        raise ValueError(f"cmaes_restarts: a budget of {budget} evaluations makes no generation of {lam}")
    best, spent = (math.inf, x0.copy()), 0
    while budget - spent >= lam:
        loss, point, used = _cmaes_run(evaluate_population, x0, sigma, lam, (budget - spent) // lam, rng, stall,
                                       callback, spent)
        spent += used
        if loss < best[0]:
            best = (loss, point)
        lam *= growth
    return best[1]


# One CMA-ES run of at most ``generations`` generations of ``lam`` points, ended early where its best loss has not
# dropped by 1e-3 of itself for ``stall`` generations (None: never): (best loss, best point, evaluations)
def _cmaes_run(evaluate_population, x0: np.ndarray, sigma: float, lam: int, generations: int,
               rng: np.random.Generator, stall: int | None, callback, evaluations: int) -> tuple:
    n = x0.size
    if lam < 2 or sigma <= 0.0 or not math.isfinite(sigma):
        raise ValueError(f"cmaes needs popsize >= 2 and a finite sigma > 0, got {lam} and {sigma!r}")
    mu = lam // 2
    weights = math.log(mu + 0.5) - np.log(np.arange(1, mu + 1))
    weights /= weights.sum()
    mu_eff = 1.0 / float(weights @ weights)
    c_sigma = (mu_eff + 2.0) / (n + mu_eff + 5.0)
    d_sigma = 1.0 + 2.0 * max(0.0, math.sqrt((mu_eff - 1.0) / (n + 1.0)) - 1.0) + c_sigma
    c_c = (4.0 + mu_eff / n) / (n + 4.0 + 2.0 * mu_eff / n)
    c_1 = 2.0 / ((n + 1.3) ** 2 + mu_eff)
    c_mu = min(1.0 - c_1, 2.0 * (mu_eff - 2.0 + 1.0 / mu_eff) / ((n + 2.0) ** 2 + mu_eff))
    chi_n = math.sqrt(n) * (1.0 - 1.0 / (4.0 * n) + 1.0 / (21.0 * n * n))
    mean, C = x0.copy(), np.eye(n)
    p_sigma, p_c = np.zeros(n), np.zeros(n)
    best = (math.inf, x0.copy())
    first = evaluations
    improved = 0  # the generation of the last drop of the best loss by 1e-3 of itself
    for generation in range(1, generations + 1):
        eigenvalues, B = np.linalg.eigh(C)
        D = np.sqrt(np.maximum(eigenvalues, 1e-300))
        z = rng.standard_normal((lam, n))
        y = (z * D) @ B.T  # ~ N(0, C)
        points = mean + sigma * y
        losses = np.asarray(evaluate_population(list(points)), dtype=np.float64)
        for point, loss in zip(points, losses):
            evaluations += 1
            if callback:
                callback(evaluations, float(loss), point)
            if loss < best[0]:
                if loss < best[0] - 1e-3 * abs(best[0]) or not math.isfinite(best[0]):
                    improved = generation
                best = (float(loss), point.copy())
        if stall is not None and generation - improved >= stall:
            break
        order = np.argsort(np.where(np.isfinite(losses), losses, np.inf))[:mu]
        y_w = weights @ y[order]
        mean = mean + sigma * y_w
        C_inv_sqrt = B @ np.diag(1.0 / D) @ B.T
        p_sigma = (1.0 - c_sigma) * p_sigma + math.sqrt(c_sigma * (2.0 - c_sigma) * mu_eff) * (C_inv_sqrt @ y_w)
        h_sigma = float(np.linalg.norm(p_sigma) / math.sqrt(1.0 - (1.0 - c_sigma) ** (2 * generation))
                        < (1.4 + 2.0 / (n + 1.0)) * chi_n)
        p_c = (1.0 - c_c) * p_c + h_sigma * math.sqrt(c_c * (2.0 - c_c) * mu_eff) * y_w
        rank_mu = (y[order].T * weights) @ y[order]
        C = ((1.0 - c_1 - c_mu) * C + c_1 * (np.outer(p_c, p_c) + (1.0 - h_sigma) * c_c * (2.0 - c_c) * C)
             + c_mu * rank_mu)
        C = 0.5 * (C + C.T)
        sigma *= math.exp((c_sigma / d_sigma) * (np.linalg.norm(p_sigma) / chi_n - 1.0))
    return best[0], best[1], evaluations - first
