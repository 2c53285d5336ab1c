"""Small optimisers on a NumPy parameter vector, for losses whose gradient comes from a simulation.

``f(theta) -> (loss, gradient)``; each call is one forward + backward simulation, so they count calls, not steps.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

Objective = Callable[[np.ndarray], tuple[float, np.ndarray]]


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


def lbfgs(f: Objective, theta: np.ndarray, *, iters: int, memory: int = 10, max_step: float = 0.5,
          callback=None, first: tuple[float, np.ndarray] | None = None) -> np.ndarray:
    """L-BFGS (Nocedal and Wright, alg. 7.4) with a backtracking line search that accepts any decrease; ``iters``
    counts evaluations of f (one forward + backward each), ``first`` (the loss and gradient at theta, if already
    known) among them. ``max_step`` bounds a step's largest change of any entry of theta. Assumes the loss's minimum is
    near 0 (true of fitting losses) to scale the first step."""
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
        while evals < iters:
            new_theta = theta + step * d
            new_loss, new_g = f(new_theta)
            evals += 1
            if callback:
                callback(evals, new_loss, new_theta)
            if new_loss < loss:  # any decrease: contacts make the gradient a poor predictor of the decrease
                break
            step *= 0.3
        else:
            break
        s, y = new_theta - theta, new_g - g
        if s @ y > 1e-12 * (s @ s):
            s_hist.append(s), y_hist.append(y)
            if len(s_hist) > memory:
                s_hist.pop(0), y_hist.pop(0)
        theta, loss, g = new_theta, new_loss, new_g
    return theta


@dataclass
class Smoothed:
    """A Gaussian-smoothed loss and its gradient at a point, estimated from perturbed copies (smoothed_gradient)."""

    loss: float
    """The mean loss of the copies: an estimate of the smoothed loss E[L(p + scale * eps)]."""
    grad: np.ndarray
    """The estimate of the smoothed loss's gradient, flat."""
    samples: int
    """Copies whose simulation ran (the others raised and are left out)."""
    failed: int
    """Copies whose simulation raised."""


def smoothed_gradient(evaluate_many, params, *, scale: float, samples: int, rng: np.random.Generator,
                      zeroth_order: bool = False) -> Smoothed:
    """The gradient of the loss smoothed by a Gaussian of standard deviation ``scale`` (in the parameters' units),
    L_s(p) = E[L(p + scale * eps)], eps ~ N(0, I), estimated from ``samples`` perturbed copies of ``params`` in
    antithetic pairs (eps and -eps), all evaluated as one batch: ``evaluate_many`` takes ``(params, None)``
    requests and returns results with ``loss`` and ``grad`` (or exceptions), as ``ControlTask.evaluate_many``,
    which runs them as worlds of one model.

    First order (default): the mean of the copies' tape gradients, the gradient of L_s wherever L is
    differentiable at the copies; it misses what L's jumps contribute (a trajectory whose contacts change within
    the scale). Zeroth order: mean over the pairs of (L(p + s eps) - L(p - s eps)) eps / (2 s), an unbiased
    estimate of the gradient of L_s even where L jumps (Nesterov and Spokoiny 2017), with the variance of a
    random direction in every parameter.
    """
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
    """The Adam steps of :func:`smoothed_descent` that ``budget`` simulations make with ``refine`` of them left to the
    ``local`` optimiser, ``copies`` a step; ValueError (naming the setting, the budget counted in ``unit``) where the
    copies are not antithetic pairs or the budget makes no step: checked before any simulation."""
    if copies % 2:
        raise ValueError(f"smoothed: search.population must be even (antithetic pairs), got {copies}")
    steps = (budget - refine) // copies
    if not steps:
        raise ValueError(f"smoothed: {budget} {unit}, {refine} of them left to {local}, make no step of {copies} "
                         "copies; raise iters or lower search.population/refine")
    return steps


def smoothed_descent(evaluate_many, x0: np.ndarray, *, sigma: float, step: float, copies: int, steps: int,
                     rng: np.random.Generator, failures: tuple[type[Exception], ...] = ()) -> np.ndarray:
    """Adam on the Gaussian-smoothed loss L_s(p) = E[L(p + sigma eps)] from ``x0``, ``steps`` steps of Adam's
    ``step`` (its learning rate: how far a step moves each parameter), each step's gradient from ``copies`` perturbed
    copies (:func:`smoothed_gradient`, ``evaluate_many`` as there: its batch sees every copy, so the caller records
    them and keeps the best point it met). A step whose every copy raised one of ``failures`` has an infinite loss
    and no gradient: Adam's momentum carries on. Returns Adam's best iterate (the smoothed loss's, an estimate)."""

    def smoothed(theta: np.ndarray) -> tuple[float, np.ndarray]:
        try:
            s = smoothed_gradient(evaluate_many, theta, scale=sigma, samples=copies, rng=rng)
        except failures:
            return math.inf, np.zeros_like(theta)
        return s.loss, s.grad

    return adam(smoothed, np.asarray(x0, dtype=np.float64).reshape(-1), iters=steps, lr=step)


def cmaes(evaluate_population, x0: np.ndarray, *, sigma: float, generations: int, rng: np.random.Generator,
          popsize: int | None = None, callback=None) -> np.ndarray:
    """CMA-ES (Hansen 2016, "The CMA Evolution Strategy: A Tutorial": (mu/mu_w, lambda) with cumulative step-size
    adaptation and rank-one and rank-mu covariance updates), a population method for losses whose gradient
    misleads (a trajectory that changes piece often). ``evaluate_population(points) -> losses`` evaluates a
    generation at once (as worlds of one batch: ``ControlTask.losses_worlds``; an infinite loss for a failed
    simulation); ``popsize`` defaults to 4 + floor(3 ln n). Returns the best point evaluated; ``callback(k, loss,
    point)`` sees every evaluation in order (k counts them)."""
    x0 = np.asarray(x0, dtype=np.float64).reshape(-1)
    n = x0.size
    lam = popsize or 4 + int(3 * math.log(n))
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
    evaluations = 0
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
                best = (float(loss), point.copy())
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
    return best[1]
