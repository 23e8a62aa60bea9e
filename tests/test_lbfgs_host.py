"""L-BFGS on the host (ude_fit.training.lbfgs) against analytical truth: the Rosenbrock
function's minimum, the strong or approximate Wolfe conditions on every accepted step, a
cubic's exact minimiser, a quadratic's minimum in few steps (also where the loss's rounding
hides the last of the way), and a loss that is not finite beyond a wall."""

from __future__ import annotations

import numpy as np
import pytest

from ude_fit.training import lbfgs


def _rosenbrock(x):
    a, b = x
    value = (1 - a) ** 2 + 100 * (b - a * a) ** 2
    grad = np.array([-2 * (1 - a) - 400 * a * (b - a * a), 200 * (b - a * a)])
    return value, grad


def _counting(fn):
    calls = []

    def evaluate(x):
        calls.append(np.array(x))
        return fn(x)
    return evaluate, calls


def test_rosenbrock_minimum_from_the_classical_start():
    evaluate, calls = _counting(_rosenbrock)
    r = lbfgs.run(evaluate, np.array([-1.2, 1.0]), steps=200)
    assert r.reason is None
    np.testing.assert_allclose(r.x, [1.0, 1.0], atol=1e-6)
    assert r.value < 1e-12
    assert r.evaluations == len(calls)
    # a quasi-Newton method's pace: far fewer than steepest descent's thousands
    assert r.steps < 60 and r.evaluations < 2 * r.steps + 10


@pytest.mark.parametrize("start", [(-1.2, 1.0), (2.0, -1.0), (0.0, 3.0)])
def test_every_accepted_step_meets_the_strong_or_approximate_wolfe_conditions(start):
    x = np.array(start)
    value, grad = _rosenbrock(x)
    pairs = __import__("collections").deque(maxlen=lbfgs.MEMORY)
    for _ in range(20):
        d = lbfgs._direction(grad, pairs)
        ls = lbfgs.line_search(_rosenbrock, x, value, grad, d)
        slope0 = grad @ d
        assert slope0 < 0
        if ls.step == 0.0:
            break
        new_value, new_grad = _rosenbrock(x + ls.step * d)
        assert new_value == pytest.approx(ls.value, rel=1e-14)
        if ls.approximate:
            assert lbfgs.CURVATURE * slope0 <= new_grad @ d <= (
                2 * lbfgs.SUFFICIENT_DECREASE - 1) * slope0
            assert new_value <= value + lbfgs.APPROXIMATE_RISE * abs(value)
        else:
            assert new_value <= value + lbfgs.SUFFICIENT_DECREASE * ls.step * slope0
            if ls.evaluations < lbfgs.EVALUATIONS:       # found, not the fallback
                assert abs(new_grad @ d) <= lbfgs.CURVATURE * abs(slope0) + 1e-15
        s, y = ls.step * d, new_grad - grad
        pairs.append((s, y, 1.0 / (s @ y)))
        x, value, grad = x + s, new_value, new_grad


def test_cubic_interpolation_is_exact_on_a_cubic():
    # phi(t) = t^3 - 3 t^2 + 1 has its local minimum at t = 2
    phi = lambda t: t ** 3 - 3 * t ** 2 + 1
    dphi = lambda t: 3 * t ** 2 - 6 * t
    a, b = lbfgs.Point(0.5, phi(0.5), dphi(0.5)), lbfgs.Point(3.0, phi(3.0), dphi(3.0))
    assert lbfgs._cubic_minimiser(a, b) == pytest.approx(2.0, rel=1e-12)
    assert lbfgs._cubic_minimiser(b, a) == pytest.approx(2.0, rel=1e-12)


def _quadratic(n: int, offset: float = 0.0):
    """A convex quadratic in n dimensions (plus a constant), and its minimiser."""
    rng = np.random.default_rng(0)
    q = rng.normal(size=(n, n))
    A = q @ q.T + n * np.eye(n)
    b = rng.normal(size=n)

    def quad(x):
        return offset + 0.5 * x @ A @ x - b @ x, A @ x - b
    return quad, np.linalg.solve(A, b)


def test_a_convex_quadratic_in_about_its_dimension_of_steps():
    n = 8
    quad, truth = _quadratic(n)
    r = lbfgs.run(quad, np.zeros(n), steps=3 * n)
    np.testing.assert_allclose(r.x, truth, rtol=1e-8, atol=1e-10)
    # at the minimum no descent direction the arithmetic resolves is left: the run stops
    # before its budget
    r = lbfgs.run(quad, np.zeros(n), steps=100)
    assert r.steps < 100
    np.testing.assert_allclose(r.x, truth, rtol=1e-14, atol=1e-15)


def test_past_the_losss_rounding_the_gradient_leads_on():
    # the same quadratic offset by 1e6: within about 1e-7 of the minimiser the loss's changes
    # fall below its rounding (1e6 * 2.2e-16), while its gradient still resolves the way.
    # Strict decrease alone stops there; the approximate Wolfe conditions go on to the
    # minimiser to the gradient's own rounding
    n = 8
    offset_quad, truth = _quadratic(n, offset=1e6)
    r = lbfgs.run(offset_quad, np.zeros(n), steps=60)
    assert r.approximate_steps > 0
    np.testing.assert_allclose(r.x, truth, rtol=1e-12, atol=1e-13)
    # and every rise it accepted was within the tolerance: the loss ends at the minimum's
    assert r.value <= offset_quad(truth)[0] + lbfgs.APPROXIMATE_RISE * 1e6


def test_a_loss_not_finite_beyond_a_wall_is_a_step_too_long():
    # a bowl about (8, 0) that is NaN wherever x[0] > 5: the run stays on the finite side,
    # up against the wall (an unconstrained method: it need not reach the wall's lowest point)
    def walled(x):
        if x[0] > 5.0:
            return np.nan, np.full(2, np.nan)
        return float(np.sum((x - [8.0, 0.0]) ** 2)), 2 * (x - [8.0, 0.0])
    r = lbfgs.run(walled, np.array([0.0, 1.0]), steps=50)
    assert r.reason is None and np.isfinite(r.value)
    assert r.x[0] <= 5.0 and r.x[0] > 4.9
    assert r.value < walled(np.array([4.9, 1.0]))[0]


def test_a_start_where_the_loss_is_not_finite_fails_with_its_reason():
    r = lbfgs.run(lambda x: (np.inf, np.zeros(2)), np.zeros(2), steps=10)
    assert r.reason == "loss is not finite at L-BFGS step 1"
    assert np.isnan(r.value) and r.steps == 0


def test_progress_every_tenth_step_and_at_the_last():
    seen = []
    lbfgs.run(_rosenbrock, np.array([-1.2, 1.0]), steps=25,
              on_step=lambda k, v: seen.append(k))
    assert seen == [10, 20, 25]


def test_flat_round_trip_keeps_the_tree():
    import jax.numpy as jnp
    tree = {"a": jnp.arange(6.0).reshape(2, 3), "b": None, "c": (jnp.ones(2), jnp.zeros(()))}
    flat = lbfgs.Flat(tree)
    x = flat.vector(tree)
    assert x.shape == (9,) and x.dtype == np.float64
    back = flat.tree(x + 1.0)
    assert back["b"] is None
    np.testing.assert_array_equal(np.asarray(back["a"]), np.arange(6.0).reshape(2, 3) + 1)
    assert np.asarray(back["c"][1]).shape == ()
