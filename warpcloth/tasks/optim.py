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
