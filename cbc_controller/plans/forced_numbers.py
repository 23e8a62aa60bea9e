"""The numbers of the forced plan: invasiveness of a control, the sustaining forcing, the
Fourier fit of a record, the board's control law, the Picard step on the target's harmonics,
and the slopes of the (A, Phi) curve through a few points."""

from __future__ import annotations

import math

import numpy as np

from ..harmonics import NH

HIGHER = [0] + list(range(2, NH + 1)) + list(range(NH + 2, 2 * NH + 1))   # DC, harmonics 2..7


def zero_targets() -> dict:
    t = {"target_a0": 0.0}
    for k in range(1, NH + 1):
        t[f"target_a{k}"] = 0.0
        t[f"target_b{k}"] = 0.0
    return t


def invasiveness(coef, var=None, navg: int = 1) -> tuple[float, float, float]:
    """(residual, fundamental, standard error of the residual) of a control's 15
    coefficients: residual = norm of its DC and harmonics 2..7, fundamental =
    hypot(c1, s1); the standard error from the per-period variances (0 without)."""
    c = np.asarray(coef, dtype=float)
    resid = float(np.sqrt(np.sum(c[HIGHER] ** 2)))
    fund = float(math.hypot(c[1], c[1 + NH]))
    se = 0.0
    if var is not None:
        v = np.maximum(np.asarray(var, dtype=float)[HIGHER], 0.0)
        se = float(np.sqrt(np.sum(v) / max(navg, 1)))
    return resid, fund, se


def forcing_of(coef, var=None, navg: int = 1) -> tuple[float, float]:
    """(Phi, its standard error): the first-harmonic amplitude of an excitation."""
    e = np.asarray(coef, dtype=float)
    phi = float(math.hypot(e[1], e[1 + NH]))
    if var is None or phi <= 0:
        return phi, 0.0
    v = np.asarray(var, dtype=float)
    s2 = (e[1] ** 2 * max(v[1], 0.0) + e[1 + NH] ** 2 * max(v[1 + NH], 0.0)) / phi ** 2
    return phi, float(math.sqrt(s2 / max(navg, 1)))


def record_fourier(samples: dict | None, forcing_amplitude: float) -> dict | None:
    """Least-squares Fourier series (a0, a1..a7, b1..b7) over the recorded forcing
    phase of the response, the control and the total excitation (forcing
    ``parameter`` cos(phase) + control: exact for the amplitude of its fundamental
    when the host forcing is 0, and without actuator latency otherwise). None when
    there are too few samples."""
    if not samples or samples.get("x") is None or len(samples["x"]) < 8 * (2 * NH + 1):
        return None
    th = np.asarray(samples["phase"], dtype=float)
    B = np.empty((th.size, 2 * NH + 1))
    B[:, 0] = 1.0
    for k in range(1, NH + 1):
        B[:, k] = np.cos(k * th)
        B[:, k + NH] = np.sin(k * th)
    u = np.asarray(samples["control"], dtype=float)
    par = np.asarray(samples.get("parameter", np.zeros_like(u)), dtype=float)
    exc = u + (par * np.cos(th) if forcing_amplitude != 0 else 0.0)
    Y = np.column_stack([np.asarray(samples["x"], dtype=float), u, exc])
    coef, *_ = np.linalg.lstsq(B, Y, rcond=None)
    resid = Y - B @ coef
    # standard errors of the coefficients from the fit residual (white-noise model)
    dof = max(th.size - B.shape[1], 1)
    s2 = np.sum(resid ** 2, axis=0) / dof
    cov_diag = np.diag(np.linalg.inv(B.T @ B))
    out = {}
    for j, ch in enumerate(("response", "control", "excitation")):
        out[ch] = {"mean": coef[:, j], "var_of_mean": s2[j] * cov_diag}
    out["samples"] = int(th.size)
    return out


def controller_response(k: int, f: float, o, sample_rate: float) -> complex:
    """The board's control law at harmonic k of f: u_k = C (target_k - x_k) for the
    complex coefficient a - i b; PD through the optional one-pole error filter
    (discrete, as the board runs it at `sample_rate`)."""
    w = 2 * math.pi * f * k
    C = o.kp + 1j * w * o.kd
    fc = o.filter_hz
    if fc > 0:
        dt = 1.0 / sample_rate
        a = 1.0 - math.exp(-2 * math.pi * fc * dt)
        C *= a / (1.0 - (1.0 - a) * complex(math.cos(w * dt), -math.sin(w * dt)))
    return C


def picard_update(T: np.ndarray, control, response, f: float, o,
                  sample_rate: float) -> np.ndarray:
    """One Picard step: DC and harmonics 2..7 of the target <- the response's.

    With ``picard_from_control`` (default) the response harmonics are read through
    the controller: x_k = T_k - u_k / C(k w), u_k the control's coefficient.
    That is the same quantity as the response channel's x_k, but the board's
    estimator leaks ~0.05 % of a signal's fundamental into each harmonic when a
    forcing period is not a whole number of samples; put into the target and
    multiplied by the controller's gain at the high harmonics (|C(7w)| ~ 5e4 1/s^2)
    that leak alone is a control residual of several per cent of the forcing at the
    jump-down fold. Through the control channel the leak is divided by |C| instead.
    """
    T = T.copy()
    r = np.asarray(response, dtype=float)
    if not o.picard_from_control:
        T[HIGHER] = r[HIGHER]
        return T
    u = np.asarray(control, dtype=float)
    T[0] = T[0] - u[0] / o.kp if o.kp != 0 else r[0]   # kp = 0: DC is not controlled
    for k in range(2, NH + 1):
        C = controller_response(k, f, o, sample_rate)
        zx = complex(T[k], -T[k + NH]) - complex(u[k], -u[k + NH]) / C
        T[k], T[k + NH] = zx.real, -zx.imag
    return T


def parabola(pts):
    """Coefficients (c2, c1, c0) of the parabola through three (A, Phi) points."""
    xs = [p[0] for p in pts]
    ys = [p[1] for p in pts]
    return np.polyfit(xs, ys, 2)


def slope_at_last(pts, sig) -> tuple[float, float]:
    """dPhi/dA at the last of (up to) three points from the parabola through them
    (the secant for two), and its standard error from the points' errors `sig`."""
    if len(pts) == 2:
        (x0, _), (x1, _) = pts
        w = np.array([-1.0, 1.0]) / (x1 - x0)
    else:
        (x0, _), (x1, _), (x2, _) = pts
        w = np.array([(x2 - x1) / ((x0 - x1) * (x0 - x2)),
                      (x2 - x0) / ((x1 - x0) * (x1 - x2)),
                      (2 * x2 - x0 - x1) / ((x2 - x0) * (x2 - x1))])
    y = np.array([p[1] for p in pts])
    return float(w @ y), float(np.sqrt(np.sum((w * np.asarray(sig)) ** 2)))


def centred_slope(trio, sig) -> tuple[float, float]:
    """dPhi/dA at the middle of three points (parabola) and its standard error."""
    (x0, _), (x1, _), (x2, _) = trio
    w = np.array([(x1 - x2) / ((x0 - x1) * (x0 - x2)),
                  (2 * x1 - x0 - x2) / ((x1 - x0) * (x1 - x2)),
                  (x1 - x0) / ((x2 - x0) * (x2 - x1))])
    y = np.array([p[1] for p in trio])
    return float(w @ y), float(np.sqrt(np.sum((w * np.asarray(sig)) ** 2)))
