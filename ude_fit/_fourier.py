"""The one Fourier basis of ude_fit: every orbit is a truncated Fourier series over one
period, K = 7 harmonics, coefficients in the order a0, a1..a7, b1..b7 (15 numbers per
coordinate):

    q(phi) = a0 + sum_k a_k cos(k phi) + b_k sin(k phi),    phi = 2 pi f t.

One convention everywhere: the coefficients are the LAST axis of an array ((..., 2K + 1));
:func:`evaluate` takes them so, :func:`harmonics` and :func:`fourier_fit` return them so,
and :func:`amplitude` reads the first harmonic from them.

Noise is removed as the paper does: by least squares over the whole raw record (many
periods) at the orbit's frequency ("Fourier averaging").
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import minimize_scalar

K = 7                             # harmonics kept for every orbit, everywhere
NCOEF = 2 * K + 1
REFINE_REL = 0.02                 # refine_frequency searches freq0 * (1 +- 2 %)


def _basis(phi: np.ndarray, k_max: int = K) -> np.ndarray:
    """(2k_max + 1, N) rows [1, cos phi .. cos k phi, sin phi .. sin k phi].

    Row-major on purpose: every product the fits need (A A^T, Y^T A^T, c A) is then a
    plain contiguous matrix product, ~4x faster on 100k-sample records than with the
    (N, 15) design matrix.
    """
    phi = np.asarray(phi, dtype=float).ravel()
    A = np.empty((2 * k_max + 1, phi.size))
    A[0] = 1.0
    z1 = np.exp(1j * phi)
    z = z1.copy()
    for k in range(1, k_max + 1):
        A[k] = z.real
        A[k_max + k] = z.imag
        z *= z1                     # powers by recurrence: one complex exp instead of 2K trig calls
    return A


def evaluate(coeffs, phi) -> np.ndarray:
    """The series at phases phi; coeffs (..., 2K+1) gives (..., len(phi))."""
    c = np.asarray(coeffs, dtype=float)
    kk = (c.shape[-1] - 1) // 2
    return c @ _basis(np.atleast_1d(phi), kk)


def amplitude(coeffs):
    """The first harmonic's amplitude hypot(a1, b1) of coefficients (..., 2K + 1)."""
    c = np.asarray(coeffs, dtype=float)
    kk = (c.shape[-1] - 1) // 2
    return np.hypot(c[..., 1], c[..., kk + 1])


def harmonics(samples, k_max: int = K):
    """Coefficients (..., 2 k_max + 1) of ``samples`` uniformly spaced over one period
    along axis 0 (numpy or jax arrays): the exact inverse of sampling a series of at most
    ``k_max`` harmonics at more than 2 k_max points."""
    xp = jnp if isinstance(samples, jax.Array) else np
    n = samples.shape[0]
    phi = 2 * np.pi * np.arange(n) / n
    k = np.arange(1, k_max + 1)
    C = np.cos(np.outer(phi, k))
    S = np.sin(np.outer(phi, k))
    a0 = xp.mean(samples, axis=0)
    a = 2.0 / n * xp.tensordot(C.T, samples, axes=1)
    b = 2.0 / n * xp.tensordot(S.T, samples, axes=1)
    return xp.moveaxis(xp.concatenate([a0[None], a, b], axis=0), 0, -1)


def first_harmonic_amplitude(samples) -> float:
    """The first harmonic's amplitude of samples over one period (axis 0)."""
    return float(amplitude(harmonics(np.asarray(samples), 1)))


def shift_phase(coeffs, delta: float) -> np.ndarray:
    """Coefficients of q(phi + delta): the same orbit with its phase origin moved by delta."""
    c = np.array(coeffs, dtype=float)
    kk = (c.shape[-1] - 1) // 2
    k = np.arange(1, kk + 1)
    cs, sn = np.cos(k * delta), np.sin(k * delta)
    a, b = c[..., 1:kk + 1].copy(), c[..., kk + 1:].copy()
    c[..., 1:kk + 1] = a * cs + b * sn
    c[..., kk + 1:] = b * cs - a * sn
    return c


def _fit(phi: np.ndarray, Y: np.ndarray, k_max: int = K,
         valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Least squares of the columns of Y (N, m) on the series in phi: ((m, 2k+1), rms (m,)).

    valid (N, m) bool, optional: samples each column may use (the others are ignored);
    the residual RMS is over the valid samples.
    """
    A = _basis(phi, k_max)
    YT = np.ascontiguousarray(np.asarray(Y, dtype=float).reshape(A.shape[1], -1).T)
    m = YT.shape[0]
    VT = None if valid is None else np.ascontiguousarray(np.asarray(valid, dtype=bool).T)
    G = A @ A.T
    rhs = (YT if VT is None else np.where(VT, YT, 0.0)) @ A.T        # (m, 2k+1)
    coef = np.empty((m, A.shape[0]))
    for j in range(m):
        Gj = G
        if VT is not None and not VT[j].all():
            Ax = A[:, ~VT[j]]
            Gj = G - Ax @ Ax.T                 # cheaper than re-forming it: few samples are out
        # Over whole periods the basis is nearly orthogonal (G ~ N/2 I), so the normal
        # equations are as accurate as an SVD and several times faster on 100k-sample
        # records; a record too short for that (ill-conditioned G) goes through the SVD.
        if np.linalg.cond(Gj) < 1e6:
            coef[j] = np.linalg.solve(Gj, rhs[j])
        else:
            v = slice(None) if VT is None else VT[j]
            coef[j] = np.linalg.lstsq(A[:, v].T, YT[j, v], rcond=None)[0]
    resid = YT - coef @ A
    if VT is None:
        rms = np.sqrt(np.einsum("ij,ij->i", resid, resid) / A.shape[1])
    else:
        resid[~VT] = 0.0
        rms = np.sqrt(np.einsum("ij,ij->i", resid, resid) / np.maximum(VT.sum(axis=1), 1))
    return coef, rms


def fourier_fit(t, y, freq: float, K: int = K):
    """Least-squares Fourier series (DC + K harmonics of `freq`, Hz) of a record y(t).

    The fit runs over the whole record, many periods, which is what averages the noise
    away. Returns (coeffs (2K+1,), residual RMS); y may also be (N, m), giving
    ((m, 2K+1), (m,)). Phase origin: t = t[0].
    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    if t.ndim != 1 or y.shape[0] != t.size:
        raise ValueError(f"fourier_fit: t has {t.size} samples, y has shape {y.shape}")
    if t.size < 2 * K + 2:
        raise ValueError(f"fourier_fit: {t.size} samples are too few for {2 * K + 1} coefficients")
    phi = 2.0 * np.pi * freq * (t - t[0])
    coef, rms = _fit(phi, y.reshape(t.size, -1), K)
    if y.ndim == 1:
        return coef[0], float(rms[0])
    return coef, rms


def refine_frequency(t, y, freq0: float, rel: float = REFINE_REL, harmonics: int = 3) -> float:
    """The frequency within freq0 * (1 +- rel) at which a periodic series (DC + the first
    `harmonics` harmonics) fits the record y(t) best: least squares, i.e. the maximum-
    likelihood estimate in white noise. The fundamental carries nearly all of the
    information; the next harmonics are fitted too because, left out, they bias a short
    record's estimate (~1e-3 relative over 5 periods of a signal with 5-10 % harmonics).

    A logged frequency a fraction of a per cent off smears a many-period average (the
    phase slips by 2 pi * error * periods over the record), so it is re-measured here.
    A grid finer than the spectral line width finds the right peak even where the
    bracket holds side lobes (long records); a bounded scalar search then polishes it.
    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    if t.ndim != 1 or t.size != y.size or t.size < 8 or not freq0 > 0:
        raise ValueError("refine_frequency: need matching 1-D t, y (at least 8 samples) "
                         "and freq0 > 0")
    t = t - t[0]
    y = y - y.mean()
    # the objective is narrow-band, so a 5 kHz record is decimated to ~128 samples a period
    # to keep the search cheap (the estimate's scatter grows only as sqrt(step))
    per_period = t.size / max(t[-1] * freq0, 1e-12)
    step = max(1, int(per_period // 128))
    td, yd = t[::step], y[::step]
    h = max(1, int(harmonics))

    def unexplained(f: float) -> float:
        A = _basis(2.0 * np.pi * f * td, h)
        r = A @ yd
        try:
            c = np.linalg.solve(A @ A.T, r)
        except np.linalg.LinAlgError:
            c = np.linalg.lstsq(A.T, yd, rcond=None)[0]
        return float(yd @ yd - r @ c)

    lo, hi = freq0 * (1.0 - rel), freq0 * (1.0 + rel)
    span = max(t[-1], 1e-12)
    n_grid = int(min(max(np.ceil((hi - lo) * span * 8.0), 8), 4000)) + 1
    grid = np.linspace(lo, hi, n_grid)
    vals = np.array([unexplained(f) for f in grid])
    i = int(np.argmin(vals))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, n_grid - 1)]
    res = minimize_scalar(unexplained, bounds=(a, b), method="bounded",
                          options={"xatol": 1e-8 * freq0, "maxiter": 100})
    return float(res.x) if res.fun <= vals[i] else float(grid[i])


