"""L-BFGS with a strong Wolfe line search for a handful of parameters (the 6 of a pose).

The algorithm of `torch.optim.LBFGS(lr=1, line_search_fn="strong_wolfe")` (itself after
minFunc), step for step, on a float64 numpy vector. Why not torch.optim: constructing any torch
optimiser imports torch._dynamo and sympy the first time in a process (its methods are wrapped by
`torch._disable_dynamo`), 0.9 s on a 2-core CPU, a third of a LiDAR frame's time budget, to
optimise 6 numbers (docs/lidar-method.md, "Speed, and how far round-off moves the table").
tests/test_nid.py checks that the iterates equal torch's.

The minimiser is a generator (`_minimizer`: it yields the points it needs evaluated and is sent
their values) so that `minimize_many` can run several starts in lockstep, their pending points
evaluated together: a NID evaluation on a coarse level is mostly per-call overhead, which one
batched call pays once for all starts.
"""
from __future__ import annotations

import functools
from typing import Callable, Generator

import numpy as np

Objective = Callable[[np.ndarray], tuple[float, np.ndarray]]  # x (n,) -> (value, gradient (n,))
# X (k, n), which (k,) the starts they belong to -> (values (k,), gradients (k, n))
Objectives = Callable[[np.ndarray, list[int]], tuple[np.ndarray, np.ndarray]]
# yields a point x (n,) to evaluate, is sent (value, gradient (n,)), returns its result
Steps = Generator[np.ndarray, tuple[float, np.ndarray], tuple]


def _cubic_min(x1: float, f1: float, g1: float, x2: float, f2: float, g2: float,
               bounds: tuple[float, float] | None = None) -> float:
    """Minimiser of the cubic through (x1, f1, g1) and (x2, f2, g2), clamped to bounds (default:
    between x1 and x2); their middle where the cubic has no minimum."""
    lo, hi = bounds if bounds is not None else (min(x1, x2), max(x1, x2))
    d1 = g1 + g2 - 3 * (f1 - f2) / (x1 - x2)
    d2_square = d1 * d1 - g1 * g2
    if d2_square < 0:
        return (lo + hi) / 2.0
    d2 = np.sqrt(d2_square)
    if x1 <= x2:
        x = x2 - (x2 - x1) * ((g2 + d2 - d1) / (g2 - g1 + 2 * d2))
    else:
        x = x1 - (x1 - x2) * ((g1 + d2 - d1) / (g1 - g2 + 2 * d2))
    return float(min(max(x, lo), hi))


def _strong_wolfe(x: np.ndarray, t: float, d: np.ndarray, f: float, g: np.ndarray,
                  gtd: float, max_ls: int, tolerance_change: float, c1: float = 1e-4,
                  c2: float = 0.9) -> Steps:
    """Step length t along d from x satisfying the strong Wolfe conditions: bracket, then zoom
    with cubic interpolation. Yields the points to evaluate (`Steps`); returns (value, gradient,
    t, evaluations)."""
    d_norm = float(np.abs(d).max())
    f_new, g_new = yield x + t * d
    evals, ls_iter = 1, 0
    gtd_new = float(g_new @ d)
    t_prev, f_prev, g_prev, gtd_prev = 0.0, f, g, gtd
    done = False
    while ls_iter < max_ls:  # bracket
        if f_new > f + c1 * t * gtd or (ls_iter > 1 and f_new >= f_prev):
            bracket, bf, bg, bgtd = [t_prev, t], [f_prev, f_new], [g_prev, g_new], [gtd_prev, gtd_new]
            break
        if abs(gtd_new) <= -c2 * gtd:
            bracket, bf, bg, bgtd = [t], [f_new], [g_new], [gtd_new]
            done = True
            break
        if gtd_new >= 0:
            bracket, bf, bg, bgtd = [t_prev, t], [f_prev, f_new], [g_prev, g_new], [gtd_prev, gtd_new]
            break
        t_next = _cubic_min(t_prev, f_prev, gtd_prev, t, f_new, gtd_new, bounds=(t + 0.01 * (t - t_prev), t * 10))
        t_prev, f_prev, g_prev, gtd_prev = t, f_new, g_new, gtd_new
        t = t_next
        f_new, g_new = yield x + t * d
        evals += 1
        gtd_new = float(g_new @ d)
        ls_iter += 1
    if ls_iter == max_ls:
        bracket, bf, bg, bgtd = [0.0, t], [f, f_new], [g, g_new], [gtd, gtd_new]

    insufficient = False
    low, high = (0, 1) if bf[0] <= bf[-1] else (1, 0)
    while not done and ls_iter < max_ls:  # zoom
        if abs(bracket[1] - bracket[0]) * d_norm < tolerance_change:
            break
        t = _cubic_min(bracket[0], bf[0], bgtd[0], bracket[1], bf[1], bgtd[1])
        # Keep t off the bracket's ends, where interpolation stalls.
        top, bottom = max(bracket), min(bracket)
        eps = 0.1 * (top - bottom)
        if min(top - t, t - bottom) < eps:
            if insufficient or t >= top or t <= bottom:
                t = top - eps if abs(t - top) < abs(t - bottom) else bottom + eps
                insufficient = False
            else:
                insufficient = True
        else:
            insufficient = False
        f_new, g_new = yield x + t * d
        evals += 1
        gtd_new = float(g_new @ d)
        ls_iter += 1
        if f_new > f + c1 * t * gtd or f_new >= bf[low]:
            bracket[high], bf[high], bg[high], bgtd[high] = t, f_new, g_new, gtd_new
            low, high = (0, 1) if bf[0] <= bf[1] else (1, 0)
        else:
            if abs(gtd_new) <= -c2 * gtd:
                done = True
            elif gtd_new * (bracket[high] - bracket[low]) >= 0:
                bracket[high], bf[high], bg[high], bgtd[high] = bracket[low], bf[low], bg[low], bgtd[low]
            bracket[low], bf[low], bg[low], bgtd[low] = t, f_new, g_new, gtd_new
    return bf[low], bg[low], bracket[low], evals


def minimize(fun: Objective, x0: np.ndarray, max_iter: int) -> tuple[np.ndarray, int]:
    """Minimise fun from x0 (n,) with at most max_iter iterations and max_iter * 5 // 4
    evaluations. Returns (x, iterations)."""
    steps = _minimizer(x0, max_iter)
    x = next(steps)
    try:
        while True:
            x = steps.send(fun(x))
    except StopIteration as done:
        return done.value


def minimize_many(fun: Objectives, x0s: np.ndarray, max_iter: int,
                  small: Callable[[int, np.ndarray], bool] | None = None) -> list[tuple[np.ndarray, int] | None]:
    """`minimize` from each start of x0s (B, n) in lockstep: each round, fun evaluates every
    unfinished start's pending point in one call (`Objectives`). A start whose value is not finite
    drops out; one stops where small(start, d) holds for its next quasi-Newton step d (n,)
    (default: never).
    Returns per start (x, iterations), or None for one that dropped out; each start's iterates
    are those `minimize` takes from it alone, given the same values."""
    runs = [_minimizer(x0, max_iter, None if small is None else functools.partial(small, k)) for k, x0 in enumerate(x0s)]
    pending = {i: next(run) for i, run in enumerate(runs)}
    out: list[tuple[np.ndarray, int] | None] = [None] * len(runs)
    while pending:
        which = list(pending)
        values, gradients = fun(np.stack([pending[i] for i in which]), which)
        for i, f, g in zip(which, values, gradients):
            del pending[i]
            if not np.isfinite(f):
                continue
            try:
                pending[i] = runs[i].send((float(f), g))
            except StopIteration as done:
                out[i] = done.value
    return out


def _minimizer(x0: np.ndarray, max_iter: int, small: Callable[[np.ndarray], bool] | None = None,
               tolerance_grad: float = 1e-9, tolerance_change: float = 1e-9, history_size: int = 100) -> Steps:
    """`minimize`'s algorithm as a generator (`Steps`), stopping where small(d) holds for the
    quasi-Newton step d (n,) it would search along next (default: never); returns (x, iterations)."""
    max_eval = max_iter * 5 // 4
    x = np.array(x0, dtype=np.float64)
    f, g = yield x
    evals = 1
    if np.abs(g).max() <= tolerance_grad:
        return x, 0
    dirs: list[np.ndarray] = []  # gradient changes y
    steps: list[np.ndarray] = []  # position changes s
    rho: list[float] = []
    h_diag, d = 1.0, -g
    n_iter = 0
    while n_iter < max_iter:
        n_iter += 1
        if n_iter > 1:
            y, s = g - g_prev, d * t
            ys = float(y @ s)
            if ys > 1e-10:  # keep the pair only where the curvature is positive
                if len(dirs) == history_size:
                    del dirs[0], steps[0], rho[0]
                dirs.append(y)
                steps.append(s)
                rho.append(1.0 / ys)
                h_diag = ys / float(y @ y)
            q, alpha = -g, [0.0] * len(dirs)
            for i in range(len(dirs) - 1, -1, -1):
                alpha[i] = float(steps[i] @ q) * rho[i]
                q = q - alpha[i] * dirs[i]
            d = q * h_diag
            for i in range(len(dirs)):
                d = d + (alpha[i] - float(dirs[i] @ d) * rho[i]) * steps[i]
            if small is not None and small(d):  # the quasi-Newton step to the minimum, as LM's update
                return x, n_iter - 1
        g_prev, f_prev = g, f
        t = min(1.0, 1.0 / float(np.abs(g).sum())) if n_iter == 1 else 1.0
        gtd = float(g @ d)
        if gtd > -tolerance_change:
            break
        f, g, t, ls_evals = yield from _strong_wolfe(x, t, d, f, g, gtd, max_eval - evals, tolerance_change)
        x = x + t * d
        evals += ls_evals
        if (n_iter == max_iter or evals >= max_eval or np.abs(g).max() <= tolerance_grad
                or np.abs(d * t).max() <= tolerance_change or abs(f - f_prev) < tolerance_change):
            break
    return x, n_iter
