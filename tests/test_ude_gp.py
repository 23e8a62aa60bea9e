"""The GP correction term (``ude_fit._gp``): accuracy, ARD, the hyperparameter fit,
differentiability of the posterior mean, and input checking.

Compile work is shared: the main fit and the subsampling test both run on
(200, 3) standardised inputs, so the L-BFGS loop is compiled for two shapes only
(that one and the tiny 1-D problem checked against scipy).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
import scipy.optimize

from ude_fit.training.gp import _nlml_fast, fit_gp, GPCorrection, neg_log_marginal_likelihood

jax.config.update("jax_enable_x64", True)       # ude_fit computes in float64 (see ude_fit docs)

SIGMA = 0.05                         # observation noise of the main data set
BOX = np.array([2.0, 3.0, 1.5])      # inputs uniform in [-BOX, BOX]
N_MAIN = 200


def _truth(Z):
    """Output 0 uses all three inputs; output 1 ignores input 2."""
    y0 = np.sin(1.5 * Z[:, 0]) + 0.3 * Z[:, 1] * np.cos(2.0 * Z[:, 2])
    y1 = np.cos(Z[:, 0]) * Z[:, 1] + 0.5 * Z[:, 0]
    return np.stack([y0, y1], axis=1)


@pytest.fixture(scope="module")
def main_fit():
    rng = np.random.default_rng(7)
    Z = rng.uniform(-1.0, 1.0, (N_MAIN, 3)) * BOX
    Y = _truth(Z) + SIGMA * rng.standard_normal((N_MAIN, 2))
    model, info = fit_gp(Z, Y, seed=0, restarts=3, steps=300)
    return Z, Y, model, info


# ----------------------------------------------------------------------------- (a) accuracy

def test_recovers_smooth_function(main_fit):
    Z, _, model, info = main_fit
    assert isinstance(model, GPCorrection)
    assert model.Z.dtype == jnp.float64 and model.alpha.shape == (N_MAIN, 2)
    assert info["n_used"] == N_MAIN and not info["subsampled"]

    rng = np.random.default_rng(123)
    Zt = rng.uniform(-0.9, 0.9, (400, 3)) * BOX
    P = np.asarray(model.predict(Zt))
    rmse = np.sqrt(np.mean((P - _truth(Zt)) ** 2, axis=0))
    # Error against the noise-free truth is well below the noise on the data.
    assert np.all(rmse < 0.75 * SIGMA), rmse
    # The fitted noise level is the one in the data.
    assert np.all((info["noise_std"] > 0.7 * SIGMA) & (info["noise_std"] < 1.4 * SIGMA)), info

    # Predictive variance: small at the data, the prior s^2 far away.
    pvar = eqx.filter_jit(lambda g, z, noise=False: g.predict_var(z, include_noise=noise))
    var_near = np.array([np.asarray(pvar(model, z)) for z in Z[:20]])
    sd_near = np.sqrt(var_near)
    # (At a training point the latent std is below the noise std; with neighbours,
    # well below: about half of it here.)
    assert np.all(sd_near < info["noise_std"]), sd_near
    assert np.all(sd_near.mean(axis=0) < 0.7 * SIGMA), sd_near
    var_far = np.asarray(pvar(model, 10.0 * BOX))
    np.testing.assert_allclose(var_far, info["signal_std"] ** 2, rtol=1e-6)
    assert np.all(var_far > 1e3 * var_near.max(axis=0))
    # With noise the variance at a training point exceeds the noise variance.
    assert np.all(np.asarray(pvar(model, Z[0], True))
                  >= info["noise_std"] ** 2)


# ----------------------------------------------------------------------------- (b) ARD

def test_ard_ignored_input_gets_long_lengthscale(main_fit):
    _, _, model, info = main_fit
    ell = info["lengthscales"]                       # (m, d), input units
    np.testing.assert_allclose(ell, np.asarray(model.lengthscales))
    # Output 1 ignores input 2: its lengthscale there is far beyond the others
    # (and far beyond the data's extent, 2 * 1.5).
    assert ell[1, 2] > 20.0 * ell[1, :2].max(), ell
    assert ell[1, 2] > 30.0 * BOX[2], ell
    # Output 0 does use input 2 (cos(2 z2)): a lengthscale of order one there.
    assert ell[0, 2] < 2.0, ell
    # The hand-written optimiser gradient in d = 3 (per-dimension lengthscale terms).
    ys = (np.asarray(main_fit[1][:, 0]) - float(model.y_mean[0])) / float(model.y_scale[0])
    th = jnp.asarray([0.1, -0.3, 0.4, 0.2, -2.0])
    args = (th, model.Z, jnp.asarray(ys), jnp.asarray(1e-6))
    np.testing.assert_allclose(jax.jit(jax.grad(_nlml_fast))(*args),
                               jax.jit(jax.grad(neg_log_marginal_likelihood))(*args), rtol=1e-8)


# ----------------------------------------------------------------------------- (c) objective

def _np_nlml(theta, Zs, y, floor=1e-6):
    """Independent numpy/scipy negative log marginal likelihood, same parametrisation."""
    d = Zs.shape[1]
    ell, s2 = np.exp(theta[:d]), np.exp(2.0 * theta[d])
    noise = floor + np.exp(2.0 * theta[d + 1]) + 1e-10 * s2
    diff = (Zs[:, None, :] - Zs[None, :, :]) / ell
    K = s2 * np.exp(-0.5 * np.sum(diff ** 2, -1)) + noise * np.eye(len(y))
    try:
        c, low = scipy.linalg.cho_factor(K, lower=True)
    except np.linalg.LinAlgError:
        return 1e10
    a = scipy.linalg.cho_solve((c, low), y)
    return 0.5 * y @ a + np.sum(np.log(np.diag(c))) + 0.5 * len(y) * np.log(2 * np.pi)


def test_hyperparameters_maximise_marginal_likelihood():
    rng = np.random.default_rng(3)
    x = np.sort(rng.uniform(0.0, 5.0, 25))
    y = np.sin(2.0 * x) + 0.5 * x + 0.1 * rng.standard_normal(25)
    model, info = fit_gp(x[:, None], y, seed=1, restarts=3)

    assert info["lml_per_restart"].shape == (1, 3)
    # The fit improves on every initial guess (restart 0 is the default guess).
    assert np.all(info["lml"][0] > info["lml_init"][0] + 1.0), info
    assert np.all(info["lml_per_restart"][0] <= info["lml"][0] + 1e-12)

    Zs = np.asarray(model.Z)
    ys = (y - float(model.y_mean[0])) / float(model.y_scale[0])
    theta = np.concatenate([np.asarray(model.log_lengthscales[0]),
                            [float(model.log_signal[0]),
                             0.5 * np.log(np.exp(2 * float(model.log_noise[0])) - 1e-6)]])

    # Same objective: the JAX function agrees with the independent numpy one.
    for th in (theta, theta + np.array([0.3, -0.2, 0.5])):
        ours = neg_log_marginal_likelihood(jnp.asarray(th), jnp.asarray(Zs), jnp.asarray(ys))
        np.testing.assert_allclose(float(ours), _np_nlml(th, Zs, ys), rtol=1e-9)
    np.testing.assert_allclose(-_np_nlml(theta, Zs, ys), info["lml"][0], rtol=1e-9)
    # The optimiser's hand-written gradient equals reverse-mode through the Cholesky.
    grad_ad = jax.jit(jax.grad(neg_log_marginal_likelihood))
    grad_fast = jax.jit(jax.grad(_nlml_fast))
    fl = jnp.asarray(1e-6)
    for th in (theta, theta + np.array([0.3, -0.2, 0.5]), np.array([-1.0, 0.7, -6.0])):
        args = (jnp.asarray(th), jnp.asarray(Zs), jnp.asarray(ys), fl)
        np.testing.assert_allclose(grad_fast(*args), grad_ad(*args), rtol=1e-8, atol=1e-10)

    # Brute force: grid over (log l, log s, log sigma_n), polished by Nelder-Mead.
    grid = (slice(-2.0, 1.5, 0.35), slice(-1.5, 1.5, 0.3), slice(-5.0, 0.0, 0.5))
    th_bf = scipy.optimize.brute(_np_nlml, grid, args=(Zs, ys), finish=None)
    res = scipy.optimize.minimize(_np_nlml, th_bf, args=(Zs, ys), method="Nelder-Mead",
                                  options={"xatol": 1e-8, "fatol": 1e-10, "maxiter": 4000})
    assert res.success
    # Same optimum: same value, same hyperparameters; scipy does not beat the fit.
    assert -res.fun <= info["lml"][0] + 1e-7
    np.testing.assert_allclose(-res.fun, info["lml"][0], atol=1e-6)
    np.testing.assert_allclose(theta, res.x, atol=1e-4)


# ----------------------------------------------------------------------------- (d) JAX transforms

def test_call_is_jittable_and_differentiable(main_fit):
    Z, _, model, _ = main_fit
    g = model.mean_only()
    assert g.chol is None
    z0 = jnp.asarray(Z[5] * 0.7 + 0.1)

    f_jit = jax.jit(lambda z: g(z))
    np.testing.assert_allclose(f_jit(z0), model(z0), rtol=1e-10)
    assert f_jit(z0).shape == (2,) and f_jit(z0).dtype == jnp.float64
    # The model as a traced argument (the way to hand it to an ODE right-hand side).
    f_arg = eqx.filter_jit(lambda gp, z: gp(z))
    np.testing.assert_allclose(f_arg(g, z0), model(z0), rtol=1e-10)
    np.testing.assert_allclose(model.predict(Z[:4]), np.stack([model(z) for z in Z[:4]]),
                               rtol=1e-10)

    J = jax.jit(jax.jacfwd(g))(z0)
    assert J.shape == (2, 3)
    h = 1e-4                      # central differences: O(h^2) ~ 1e-7 error here
    J_fd = np.stack([(np.asarray(g(z0 + h * e)) - np.asarray(g(z0 - h * e))) / (2 * h)
                     for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(J, J_fd, rtol=1e-6, atol=1e-6)
    # And against the truth's derivative, loosely (output 1 = cos(z0) z1 + z0/2).
    true_J1 = np.array([-np.sin(z0[0]) * z0[1] + 0.5, np.cos(z0[0]), 0.0])
    np.testing.assert_allclose(J[1], true_J1, atol=0.15)
    with pytest.raises(ValueError, match="mean-only"):
        g.predict_var(z0)


# ----------------------------------------------------------------------------- subsampling

def test_subsampling_is_seeded_and_reported():
    rng = np.random.default_rng(11)
    Z = rng.uniform(-1.0, 1.0, (260, 3)) * BOX
    y = _truth(Z)[:, 1] + SIGMA * rng.standard_normal(260)
    m1, i1 = fit_gp(Z, y, seed=4, restarts=1, steps=20, max_points=N_MAIN)
    m2, _ = fit_gp(Z, y, seed=4, restarts=1, steps=20, max_points=N_MAIN)
    m3, _ = fit_gp(Z, y, seed=5, restarts=1, steps=20, max_points=N_MAIN)
    assert i1["subsampled"] and i1["n_used"] == N_MAIN and i1["n_total"] == 260
    assert "subsampled" in i1["note"]
    assert m1.alpha.shape == (N_MAIN, 1) and m1(Z[0]).shape == (1,)
    np.testing.assert_array_equal(m1.Z, m2.Z)
    assert not np.array_equal(np.asarray(m1.Z), np.asarray(m3.Z))


# ----------------------------------------------------------------------------- (e) bad input

_GOOD_Z = np.random.default_rng(0).standard_normal((10, 2))
_GOOD_Y = np.random.default_rng(1).standard_normal((10, 1))


@pytest.mark.parametrize("Z, Y, match", [
    (_GOOD_Z[:, 0], _GOOD_Y, "must be"),
    (_GOOD_Z[None], _GOOD_Y, "must be"),
    (_GOOD_Z, _GOOD_Y[None], "must be"),
    (_GOOD_Z, _GOOD_Y[:9], "rows"),
    (_GOOD_Z[:4], _GOOD_Y[:4], "at least"),
    (np.where(np.eye(10, 2) > 0, np.nan, _GOOD_Z), _GOOD_Y, "NaN"),
    (_GOOD_Z, np.where(np.eye(10, 1) > 0, np.inf, _GOOD_Y), "NaN or inf"),
    (_GOOD_Z.astype(str).astype(object) + "x", _GOOD_Y, "numeric"),
    (np.zeros((10, 0)), _GOOD_Y, "empty"),
])
def test_bad_input(Z, Y, match):
    with pytest.raises(ValueError, match=match) as exc:
        fit_gp(Z, Y)
    assert "\n" not in str(exc.value)
