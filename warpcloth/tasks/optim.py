"""Small optimisers on a NumPy parameter vector, for losses whose gradient comes from a simulation.

``f(theta) -> (loss, gradient)``; each call is one forward + backward simulation, so they count calls, not steps.
"""

from __future__ import annotations

import math
from collections.abc import Callable

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
