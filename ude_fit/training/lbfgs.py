"""L-BFGS on the host: numpy's vector algebra around one compiled value-and-gradient.

Why on the host: compiled as one step (optax's), L-BFGS traces the loss's value and gradient
three times (its check of a stored value and both phases of its line search), and XLA
compiles each copy: for the constraint rounds' loss that step took about 110 s to compile,
more than the rest of a fit's compilation. Here the loss's value and gradient are compiled
once and shared with Adam's one-set steps (:mod:`.optimise`); each evaluation is one call,
whose dispatch (well under a millisecond) is small against the 20-60 ms an evaluation of
the shooting losses costs on 2 cores.

The method is the textbook one (Nocedal & Wright, *Numerical Optimization*, 2nd ed., 2006):
the two-loop recursion over the last :data:`MEMORY` pairs with the initial inverse Hessian
s'y / y'y (Alg. 7.4, eq. 7.20), a line search that meets the strong Wolfe conditions with
c1 = 1e-4 and c2 = 0.9 (Alg. 3.5 and 3.6, trial steps by safeguarded cubic interpolation),
and a pair kept only where its curvature s'y is positive, so the approximation stays
positive definite.

A trial step is also accepted where it meets the *approximate* Wolfe conditions (Hager &
Zhang, SIAM J. Optim. 16, 2005, eq. 4.1 with their epsilon = 1e-6): a slope along the line
between c2 and (1 - 2 c1) times the first one's magnitude, and a loss at most 1e-6 of its
magnitude above the first. On a quadratic the slope condition is the sufficient-decrease
condition itself, read from the gradient; it matters near a minimum, where the loss's
changes fall below its rounding while its gradient still points the way (measured on
lee2020/model2, 2026-12-02: no step of the fits' L-BFGS runs needed it).

The first direction is the gradient scaled to a step of at most unit length. A non-finite
loss on the line counts as a step too long. Where no step along the L-BFGS direction lowers
the loss, the memory is cleared and the gradient tried; where that fails too, no step that
the loss or its slope can resolve is left and the run stops there. The run also stops after
:data:`MEMORY` steps in a row that reach neither a loss nor a gradient norm lower than any
before: at a minimum to the arithmetic's rounding the accepted steps only circle among
rounded points (measured on a quadratic: the rounding of the loss's last digit passes for a
decrease, and points come back exactly), where the loss falling or the gradient shrinking,
as it does on every step of a run still on its way, keeps it going.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

MEMORY = 10                  # (s, y) pairs kept
SUFFICIENT_DECREASE = 1e-4   # c1 of the Wolfe conditions
CURVATURE = 0.9              # c2: a loose line search, as quasi-Newton methods want
EVALUATIONS = 20             # at most, per line search
EXPANSION = 2.0              # the bracketing phase's growth of the trial step
APPROXIMATE_RISE = 1e-6      # the approximate Wolfe conditions' tolerated rise, relative


def _value_and_grad(params, loss, args):
    return jax.value_and_grad(loss)(params, *args)


# one compilation per loss and argument structure, shared by every caller (Adam's one-set
# steps in .optimise as well)
value_and_grad = eqx.filter_jit(_value_and_grad)


class Flat:
    """Between a tree of float arrays and one float64 vector (its leaves in order)."""

    def __init__(self, tree):
        leaves, self.treedef = jax.tree_util.tree_flatten(tree)
        self.shapes = [np.shape(x) for x in leaves]
        self.splits = np.cumsum([int(np.prod(s)) for s in self.shapes])[:-1]

    def vector(self, tree) -> np.ndarray:
        leaves = jax.tree_util.tree_leaves(tree)
        return np.concatenate([np.asarray(x, np.float64).ravel() for x in leaves])

    def tree(self, x: np.ndarray):
        parts = np.split(x, self.splits)
        return jax.tree_util.tree_unflatten(
            self.treedef, [jnp.asarray(p.reshape(s)) for p, s in zip(parts, self.shapes)])


class Point(NamedTuple):
    """A point on the search line: step length, loss, slope along the direction."""
    step: float
    value: float
    slope: float


def _finite(value: float, grad: np.ndarray) -> bool:
    return bool(np.isfinite(value) and np.all(np.isfinite(grad)))


def _cubic_minimiser(a: Point, b: Point) -> float:
    """The minimiser of the cubic through two points' values and slopes (N&W eq. 3.59), or
    NaN where it has none."""
    d1 = a.slope + b.slope - 3.0 * (a.value - b.value) / (a.step - b.step)
    disc = d1 * d1 - a.slope * b.slope
    if not np.isfinite(disc) or disc < 0.0:
        return np.nan
    d2 = np.sign(b.step - a.step) * np.sqrt(disc)
    return b.step - (b.step - a.step) * (b.slope + d2 - d1) / (b.slope - a.slope + 2.0 * d2)


def _trial(lo: Point, hi: Point) -> float:
    """The next trial step inside the bracket [lo, hi]: the cubic's minimiser where it lies
    well inside, else the midpoint (also where ``hi`` was not finite, so has no slope)."""
    width = abs(hi.step - lo.step)
    left, right = min(lo.step, hi.step), max(lo.step, hi.step)
    if np.isfinite(hi.value) and np.isfinite(hi.slope):
        a = _cubic_minimiser(lo, hi)
        if np.isfinite(a) and left + 0.1 * width < a < right - 0.1 * width:
            return float(a)
    return 0.5 * (lo.step + hi.step)


class LineResult(NamedTuple):
    step: float              # 0.0: no step lowered the loss
    value: float
    grad: np.ndarray
    evaluations: int
    approximate: bool = False    # accepted by the approximate Wolfe conditions alone


def line_search(evaluate: Callable, x: np.ndarray, value: float, grad: np.ndarray,
                direction: np.ndarray, first_step: float = 1.0) -> LineResult:
    """A step along ``direction`` (a descent direction at ``x``) meeting the strong or the
    approximate Wolfe conditions; where :data:`EVALUATIONS` trials find none, the lowest
    trial that meets the sufficient-decrease condition, else step 0."""
    slope0 = float(grad @ direction)
    best = LineResult(0.0, value, grad, 0)
    count = 0

    def at(step):
        nonlocal best, count
        v, g = evaluate(x + step * direction)
        count += 1
        if not _finite(v, g):
            return Point(step, np.inf, np.nan), None, False
        p = Point(step, float(v), float(g @ direction))
        # strictly lower as well: where the slope is below the loss's rounding, a step that
        # leaves it unchanged would pass the condition and go nowhere
        decrease = p.value <= value + SUFFICIENT_DECREASE * step * slope0 and p.value < value
        if decrease and p.value < best.value:
            best = LineResult(step, p.value, g, count)
        return p, g, decrease

    def wolfe(p: Point) -> bool:
        return abs(p.slope) <= -CURVATURE * slope0

    def approximately_wolfe(p: Point) -> bool:
        return (CURVATURE * slope0 <= p.slope <= (2.0 * SUFFICIENT_DECREASE - 1.0) * slope0
                and p.value <= value + APPROXIMATE_RISE * abs(value))

    # bracketing (Alg. 3.5): grow the step until an interval holds a Wolfe point
    prev, step = Point(0.0, value, slope0), first_step
    lo = hi = None
    while count < EVALUATIONS:
        p, g, decrease = at(step)
        if approximately_wolfe(p) and not decrease:
            return LineResult(p.step, p.value, g, count, approximate=True)
        if not decrease or p.value >= prev.value and prev.step > 0.0:
            lo, hi = prev, p
            break
        if wolfe(p):
            return LineResult(p.step, p.value, g, count)
        if p.slope >= 0.0:
            lo, hi = p, prev
            break
        prev, step = p, EXPANSION * step
    # zoom (Alg. 3.6): shrink the interval about the Wolfe points it holds
    while lo is not None and count < EVALUATIONS:
        if abs(hi.step - lo.step) <= 1e-12 * max(1.0, abs(lo.step)):
            break
        p, g, decrease = at(_trial(lo, hi))
        if approximately_wolfe(p) and not decrease:
            return LineResult(p.step, p.value, g, count, approximate=True)
        if not decrease or p.value >= lo.value:
            hi = p
            continue
        if wolfe(p):
            return LineResult(p.step, p.value, g, count)
        if p.slope * (hi.step - lo.step) >= 0.0:
            hi = lo
        lo = p
    return best._replace(evaluations=count)


def _direction(grad: np.ndarray, pairs: deque) -> np.ndarray:
    """-H grad by the two-loop recursion (N&W Alg. 7.4); without pairs, the gradient scaled
    to a step of at most unit length."""
    if not pairs:
        return -grad * min(1.0, 1.0 / max(float(np.linalg.norm(grad)), 1e-300))
    q = grad.copy()
    alphas = []
    for s, y, rho in reversed(pairs):
        a = rho * float(s @ q)
        q -= a * y
        alphas.append(a)
    s, y, _ = pairs[-1]
    q *= float(s @ y) / float(y @ y)
    for (s, y, rho), a in zip(pairs, reversed(alphas)):
        q += (a - rho * float(y @ q)) * s
    return -q


class RunResult(NamedTuple):
    x: np.ndarray
    value: float             # the loss at x (NaN where the run failed)
    reason: str | None       # why it failed: the loss not finite where it started
    steps: int               # steps taken (fewer than asked where no step was left)
    evaluations: int
    approximate_steps: int = 0   # of them, accepted by the approximate Wolfe conditions


def run(evaluate: Callable, x: np.ndarray, steps: int,
        on_step: Callable[[int, float], None] = lambda k, v: None) -> RunResult:
    """At most ``steps`` L-BFGS steps from ``x`` on ``evaluate(x) -> (loss, gradient)``.
    ``on_step(k, loss)`` every tenth step and at the last."""
    value, grad = evaluate(x)
    evaluations = 1
    value = float(value)
    if not _finite(value, grad):
        return RunResult(x, np.nan, "loss is not finite at L-BFGS step 1", 0, evaluations)
    pairs: deque = deque(maxlen=MEMORY)
    k = approximate = stalled = 0
    lowest_value, lowest_norm = value, float(np.linalg.norm(grad))
    while k < steps:
        d = _direction(grad, pairs)
        if not float(grad @ d) < 0.0:          # rounding made it no descent direction
            pairs.clear()
            d = _direction(grad, pairs)
            if not float(grad @ d) < 0.0:      # the gradient is zero: a stationary point
                break
        ls = line_search(evaluate, x, value, grad, d)
        evaluations += ls.evaluations
        if ls.step == 0.0:
            if pairs:                          # the memory misled: start it again
                pairs.clear()
                continue
            break                              # no step the loss resolves is left
        k += 1
        approximate += ls.approximate
        s, y = ls.step * d, ls.grad - grad
        sy = float(s @ y)
        if sy > 1e-12 * float(np.linalg.norm(s)) * float(np.linalg.norm(y)):
            pairs.append((s, y, 1.0 / sy))
        x, value, grad = x + s, ls.value, ls.grad
        norm = float(np.linalg.norm(grad))
        stalled = 0 if value < lowest_value or norm < lowest_norm else stalled + 1
        lowest_value, lowest_norm = min(lowest_value, value), min(lowest_norm, norm)
        if k % 10 == 0 or k == steps:
            on_step(k, value)
        if stalled >= MEMORY:                  # circling at the rounding: nothing left to gain
            break
    if k < steps:
        on_step(k, value)
    return RunResult(x, value, None, k, evaluations, approximate)
