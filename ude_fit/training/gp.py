"""Gaussian-process correction term ``U(z)`` for the universal differential equation.

The GP variant of the UDE replaces the neural correction by the posterior mean of
a Gaussian process with a squared-exponential ARD kernel, fitted to residual
forces (or accelerations) sampled along measured periodic orbits::

    k(z, z') = s^2 exp(-1/2 sum_i (z_i - z'_i)^2 / l_i^2)

Inputs ``Z`` (N x d) and targets ``Y`` (N x m) are standardised (zero mean, unit
standard deviation per column); every output gets an independent GP with its own
lengthscales, signal and noise level, chosen by maximising the exact log marginal
likelihood (Cholesky) with L-BFGS (``optax.lbfgs``) from several seeded starts.

:class:`GPCorrection` is an ``equinox.Module`` whose ``__call__`` maps one feature
vector ``z`` (d,) to the posterior mean (m,) in original units. It is a pure JAX
function of ``z`` (weights ``alpha = K^-1 y`` are precomputed), so it can be jitted,
``jax.jacfwd``-ed and evaluated inside an ODE right-hand side.

Precision: float64 (the marginal likelihood and the Cholesky factor of an N ~ 1500 kernel
matrix with a 1e-6 noise floor need it); :func:`fit_gp` refuses to run without it (see
``ude_fit._precision``).

Units of the stored hyperparameters: ``log_lengthscales``, ``log_signal`` and
``log_noise`` refer to the *standardised* variables (the ones ``Z`` and ``alpha``
live in). :func:`fit_gp`'s info dict gives them in original units as well.
"""

from __future__ import annotations

import time
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
import optax

from .._precision import require_float64

__all__ = ["GPCorrection", "fit_gp", "neg_log_marginal_likelihood"]

#: relative jitter added to the kernel diagonal (times s^2) on top of the noise
_JITTER = 1e-10
_MIN_POINTS = 5


# ---------------------------------------------------------------------------------------
# kernel and objective (standardised units)
# ---------------------------------------------------------------------------------------

def _nlml_parts(theta, Z, y, noise_floor):
    """Value of the negative LML and what its gradient needs."""
    d = Z.shape[1]
    log_ell, log_s, raw = theta[:d], theta[d], theta[d + 1]
    a = Z * jnp.exp(-log_ell)
    sq = jnp.sum(a * a, -1)
    R = jnp.exp(-0.5 * jnp.maximum(sq[:, None] + sq[None, :] - 2.0 * a @ a.T, 0.0))
    s2 = jnp.exp(2.0 * log_s)
    extra = jnp.exp(2.0 * raw)                       # noise variance above the floor
    K = s2 * R + (noise_floor + extra + _JITTER * s2) * jnp.eye(Z.shape[0], dtype=R.dtype)
    L = jnp.linalg.cholesky(K)
    alpha = jsl.cho_solve((L, True), y)
    n = y.shape[0]
    val = (0.5 * jnp.dot(y, alpha) + jnp.sum(jnp.log(jnp.diagonal(L)))
           + 0.5 * n * jnp.log(2.0 * jnp.pi))
    return val, (L, alpha, a, R, s2, extra)


def neg_log_marginal_likelihood(theta, Z, y, noise_floor=1e-6):
    """Exact negative log marginal likelihood of one output.

    ``theta = (log l_1..log l_d, log s, raw_log_noise)`` in standardised units; the
    noise variance is ``noise_floor + exp(2 raw_log_noise)`` (plus a 1e-10 s^2
    jitter). ``Z`` (N,d), ``y`` (N,). Returns ``1/2 y^T K^-1 y + 1/2 log|K| +
    N/2 log(2 pi)``. Plain JAX (differentiable in every argument); the optimiser
    uses the same value with a hand-written gradient in ``theta``.
    """
    return _nlml_parts(theta, Z, y, noise_floor)[0]


@jax.custom_vjp
def _nlml_fast(theta, Z, y, noise_floor):
    """Same value as :func:`neg_log_marginal_likelihood`; analytic gradient in theta only.

    The gradient 1/2 tr((K^-1 - alpha alpha^T) dK/dtheta) costs one extra
    Cholesky solve, about half what reverse-mode through the Cholesky costs at
    N = 1500. Cotangents for ``Z``, ``y`` and ``noise_floor`` are zero (not used).
    """
    return _nlml_parts(theta, Z, y, noise_floor)[0]


def _nlml_fast_fwd(theta, Z, y, noise_floor):
    val, res = _nlml_parts(theta, Z, y, noise_floor)
    return val, (res, Z, y, noise_floor)


def _nlml_fast_bwd(res, g):
    (L, alpha, a, R, s2, extra), Z, y, noise_floor = res
    W = jsl.cho_solve((L, True), jnp.eye(L.shape[0], dtype=L.dtype)) - jnp.outer(alpha, alpha)
    M = (s2 * R) * W
    rows = jnp.sum(M, axis=1)
    # d K / d log l_k = K_f o (a_ik - a_jk)^2 ;  sum_ij M_ij (a_ik - a_jk)^2 / 2:
    g_ell = (a * a).T @ rows - jnp.sum(a * (M @ a), axis=0)
    trW = jnp.trace(W)
    g_s = jnp.sum(M) + _JITTER * s2 * trW
    g_raw = extra * trW
    grad = jnp.concatenate([g_ell, jnp.stack([g_s, g_raw])]) * g
    return grad, jnp.zeros_like(Z), jnp.zeros_like(y), jnp.zeros_like(noise_floor)


_nlml_fast.defvjp(_nlml_fast_fwd, _nlml_fast_bwd)


@jax.jit
def _optimise(theta0, Z, y, noise_floor, max_iter, gtol, ftol):
    """L-BFGS on the per-point negative LML. Returns (theta, nlml, iterations).

    Stops after ``max_iter`` iterations, when the gradient norm drops below
    ``gtol``, or when an iteration lowers the objective by less than ``ftol``
    relative (scipy's L-BFGS-B criterion), whichever comes first.
    """
    n = y.shape[0]

    def fun(th):
        return _nlml_fast(th, Z, y, noise_floor) / n

    opt = optax.lbfgs()
    value_and_grad = optax.value_and_grad_from_state(fun)

    def step(carry):
        th, state, _ = carry
        value, grad = value_and_grad(th, state=state)
        updates, state = opt.update(grad, state, th, value=value, grad=grad,
                                    value_fn=fun)
        return optax.apply_updates(th, updates), state, value

    def going(carry):
        _, state, prev = carry
        it = optax.tree.get(state, "count")
        g = optax.tree.get(state, "grad")
        v = optax.tree.get(state, "value")
        ok = jnp.isfinite(v) & jnp.all(jnp.isfinite(g))
        small_step = (prev - v) <= ftol * jnp.maximum(jnp.maximum(jnp.abs(prev), jnp.abs(v)), 1.0)
        return (it <= 1) | ((it < max_iter) & (optax.tree.norm(g) >= gtol) & ~small_step & ok)

    carry = (theta0, opt.init(theta0), jnp.asarray(jnp.inf, dtype=theta0.dtype))
    th, state, _ = jax.lax.while_loop(going, step, carry)
    return th, fun(th) * n, optax.tree.get(state, "count")


@jax.jit
def _nlml(theta, Z, y, noise_floor):
    return neg_log_marginal_likelihood(theta, Z, y, noise_floor)


@jax.jit
def _weights(theta, Z, y, noise_floor):
    _, (L, alpha, *_rest) = _nlml_parts(theta, Z, y, noise_floor)
    return L, alpha


# ---------------------------------------------------------------------------------------
# the model
# ---------------------------------------------------------------------------------------

class GPCorrection(eqx.Module):
    """Fitted GP posterior; ``model(z)`` is the posterior mean (m,) at one input (d,).

    All arrays are float64. ``Z``, ``alpha``, ``chol`` and the log hyperparameters are
    in standardised units (see the module docstring); ``z_mean``/``z_scale`` and
    ``y_mean``/``y_scale`` map between those and original units. ``chol`` (m,N,N) is
    only needed by :meth:`predict_var`; :meth:`mean_only` drops it.
    """
    Z: jax.Array                 # (N, d) standardised training inputs
    alpha: jax.Array             # (N, m) K^-1 y per output
    log_lengthscales: jax.Array  # (m, d)
    log_signal: jax.Array        # (m,)  log s
    log_noise: jax.Array         # (m,)  log of the noise std (floor included)
    z_mean: jax.Array            # (d,)
    z_scale: jax.Array           # (d,)
    y_mean: jax.Array            # (m,)
    y_scale: jax.Array           # (m,)
    chol: Optional[jax.Array] = None  # (m, N, N) lower Cholesky factors of K + noise

    @property
    def n_inputs(self) -> int:
        return self.Z.shape[1]

    @property
    def n_outputs(self) -> int:
        return self.alpha.shape[1]

    def _kvec(self, z):
        """Cross-covariances k(Z, z): (m, N), standardised units.

        Written as |a|^2 + |b|^2 - 2 a.b (matrix-vector products) rather than via
        the (m, N, d) difference array: 3-4x cheaper inside a jitted ODE solve,
        for the value and for ``jacfwd`` alike.
        """
        zs = (z - self.z_mean) / self.z_scale
        inv = jnp.exp(-self.log_lengthscales)                     # (m, d)
        Zl = self.Z[None, :, :] * inv[:, None, :]                 # (m, N, d)
        zl = zs[None, :] * inv                                    # (m, d)
        d2 = (jnp.sum(Zl * Zl, -1) + jnp.sum(zl * zl, -1)[:, None]
              - 2.0 * jnp.einsum("mnd,md->mn", Zl, zl))
        return jnp.exp(2.0 * self.log_signal[:, None] - 0.5 * jnp.maximum(d2, 0.0))

    def __call__(self, z):
        """Posterior mean (m,) at one feature vector ``z`` (d,), original units."""
        z = jnp.asarray(z)
        k = self._kvec(z)                                          # (m, N)
        mean = jnp.sum(k * self.alpha.T, axis=-1)
        return self.y_mean + self.y_scale * mean

    def predict(self, Zq):
        """Posterior mean at a batch of inputs (n, d) -> (n, m)."""
        return jax.vmap(self)(jnp.asarray(Zq))

    def predict_var(self, z, include_noise: bool = False):
        """Posterior variance (m,) of the latent function at one input, original units.

        With ``include_noise`` the fitted observation-noise variance is added.
        Requires ``chol`` (not available after :meth:`mean_only`).
        """
        if self.chol is None:
            raise ValueError("predict_var needs the Cholesky factor; this model was made mean-only")
        k = self._kvec(jnp.asarray(z))                             # (m, N)
        v = jax.vmap(lambda L, kk: jsl.solve_triangular(L, kk, lower=True))(self.chol, k)
        var = jnp.exp(2.0 * self.log_signal) - jnp.sum(v * v, axis=-1)
        var = jnp.maximum(var, 0.0)
        if include_noise:
            var = var + jnp.exp(2.0 * self.log_noise)
        return var * self.y_scale ** 2

    def mean_only(self) -> "GPCorrection":
        """Copy without the (m,N,N) Cholesky factor: what to put inside an ODE RHS."""
        return eqx.tree_at(lambda g: g.chol, self, None, is_leaf=lambda x: x is None)

    @property
    def lengthscales(self):
        """Lengthscales (m, d) in original input units."""
        return jnp.exp(self.log_lengthscales) * self.z_scale[None, :]


# ---------------------------------------------------------------------------------------
# fitting
# ---------------------------------------------------------------------------------------

def _check(Z, Y):
    try:
        Z = np.asarray(Z, dtype=np.float64)
        Y = np.asarray(Y, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ValueError(f"fit_gp: Z and Y must be numeric arrays ({msg})") from None
    if Y.ndim == 1:
        Y = Y[:, None]
    if Z.ndim != 2 or Y.ndim != 2:
        raise ValueError(f"fit_gp: Z must be (N, d) and Y (N, m) or (N,); "
                         f"got {Z.shape} and {Y.shape}")
    if Z.shape[0] != Y.shape[0]:
        raise ValueError(f"fit_gp: Z has {Z.shape[0]} rows but Y has {Y.shape[0]}")
    if Z.shape[1] < 1 or Y.shape[1] < 1:
        raise ValueError(f"fit_gp: empty feature or output dimension ({Z.shape}, {Y.shape})")
    if Z.shape[0] < _MIN_POINTS:
        raise ValueError(f"fit_gp: need at least {_MIN_POINTS} points, got {Z.shape[0]}")
    if not (np.all(np.isfinite(Z)) and np.all(np.isfinite(Y))):
        raise ValueError("fit_gp: Z or Y contains NaN or inf")
    return Z, Y


def _initial_thetas(rng, d, restarts):
    """Restart 0: l = 1, s = 1, noise std 0.1 (standardised); the rest seeded random."""
    out = [np.concatenate([np.zeros(d), [0.0, np.log(0.1)]])]
    for _ in range(restarts - 1):
        log_ell = rng.uniform(np.log(0.2), np.log(5.0), size=d)
        log_s = rng.uniform(np.log(0.3), np.log(3.0))
        log_n = rng.uniform(np.log(1e-3), np.log(0.5))
        out.append(np.concatenate([log_ell, [log_s, log_n]]))
    return out


def fit_gp(Z, Y, *, seed: int = 0, restarts: int = 3, steps: int = 300,
           max_points: int = 1500, noise_floor: float = 1e-6, gtol: float = 1e-7,
           ftol: float = 1e-10
           ) -> tuple[GPCorrection, dict]:
    """Fit independent SE-ARD GPs (one per output column) to ``Z`` (N,d) -> ``Y`` (N,m).

    ``restarts`` L-BFGS runs from seeded initial guesses (restart 0 is the fixed
    guess l = 1, s = 1, noise std 0.1 in standardised units); the best marginal
    likelihood wins, per output. A run stops after ``steps`` iterations, when the
    gradient norm of the per-point negative log marginal likelihood drops below
    ``gtol``, or when an iteration improves it by less than ``ftol`` (relative).
    The noise variance is bounded below by ``noise_floor`` times the output
    variance. If N > ``max_points``, a seeded random subset of ``max_points`` rows
    is used (``info['subsampled']``).

    Returns ``(model, info)``; ``info`` holds ``lml`` (m,) and ``lml_per_restart``
    (m, restarts) and ``lml_init`` (m, restarts) (log marginal likelihoods of the
    standardised data), ``best_restart``, ``iterations``, ``lengthscales`` (m,d) in
    input units, ``signal_std`` and ``noise_std`` (m,) in output units, ``n_used``,
    ``n_total``, ``subsampled``, ``note``, ``time_s``. The log marginal likelihood
    of output j in original units is ``lml[j] - n_used * log(y_scale[j])``.
    """
    require_float64("fit_gp")
    t0 = time.perf_counter()
    Z, Y = _check(Z, Y)
    if int(restarts) < 1 or int(steps) < 1 or int(max_points) < _MIN_POINTS:
        raise ValueError("fit_gp: restarts and steps must be >= 1 and max_points >= 5")
    if not noise_floor > 0:
        raise ValueError("fit_gp: noise_floor must be > 0")
    n_total, d = Z.shape
    m = Y.shape[1]
    rng = np.random.default_rng(seed)

    subsampled = n_total > max_points
    if subsampled:
        idx = np.sort(rng.choice(n_total, size=int(max_points), replace=False))
        Z, Y = Z[idx], Y[idx]
        note = f"subsampled {max_points} of {n_total} points (seed {seed})"
    else:
        note = f"all {n_total} points used"
    n = Z.shape[0]

    z_mean = Z.mean(0)
    z_scale = Z.std(0)
    z_scale = np.where(z_scale > 0, z_scale, 1.0)
    y_mean = Y.mean(0)
    y_scale = Y.std(0)
    y_scale = np.where(y_scale > 0, y_scale, 1.0)
    Zs = jnp.asarray((Z - z_mean) / z_scale)
    Ys = (Y - y_mean) / y_scale

    inits = _initial_thetas(rng, d, int(restarts))
    floor = jnp.asarray(noise_floor, dtype=jnp.float64)
    lml_runs = np.full((m, len(inits)), -np.inf)
    lml_init = np.full((m, len(inits)), -np.inf)
    iters = np.zeros((m, len(inits)), dtype=int)
    thetas = np.zeros((m, d + 2))
    best = np.zeros(m, dtype=int)
    chols, alphas = [], []
    for j in range(m):
        y = jnp.asarray(Ys[:, j])
        best_val, best_th = np.inf, None
        for r, th0 in enumerate(inits):
            th0 = jnp.asarray(th0)
            lml_init[j, r] = -float(_nlml(th0, Zs, y, floor))
            th, val, it = _optimise(th0, Zs, y, floor, int(steps), float(gtol), float(ftol))
            val = float(val)
            iters[j, r] = int(it)
            if np.isfinite(val) and np.all(np.isfinite(np.asarray(th))):
                lml_runs[j, r] = -val
                if val < best_val:
                    best_val, best_th, best[j] = val, np.asarray(th), r
        if best_th is None:
            raise RuntimeError(f"fit_gp: every restart failed for output {j}")
        thetas[j] = best_th
        L, a = _weights(jnp.asarray(best_th), Zs, y, floor)
        chols.append(L)
        alphas.append(a)

    log_noise = 0.5 * np.log(noise_floor + np.exp(2.0 * thetas[:, d + 1]))
    model = GPCorrection(
        Z=Zs,
        alpha=jnp.stack(alphas, axis=1),
        log_lengthscales=jnp.asarray(thetas[:, :d]),
        log_signal=jnp.asarray(thetas[:, d]),
        log_noise=jnp.asarray(log_noise),
        z_mean=jnp.asarray(z_mean),
        z_scale=jnp.asarray(z_scale),
        y_mean=jnp.asarray(y_mean),
        y_scale=jnp.asarray(y_scale),
        chol=jnp.stack(chols, axis=0),
    )
    info = {
        "lml": lml_runs[np.arange(m), best],
        "lml_per_restart": lml_runs,
        "lml_init": lml_init,
        "best_restart": best,
        "iterations": iters,
        "lengthscales": np.exp(thetas[:, :d]) * z_scale[None, :],
        "signal_std": np.exp(thetas[:, d]) * y_scale,
        "noise_std": np.exp(log_noise) * y_scale,
        "n_used": n,
        "n_total": n_total,
        "subsampled": bool(subsampled),
        "note": note,
        "time_s": time.perf_counter() - t0,
    }
    return model, info
