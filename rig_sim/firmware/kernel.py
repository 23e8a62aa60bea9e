"""The board's real-time loop, compiled: one call advances the rig n samples.

Per sample, in the order a real CBC board does it:
  measure (sensor noise, ADC quantisation) -> phase (forcing or response-locked)
  -> target from its Fourier coefficients -> PD control law (optional error
  filter) -> clamp/saturate -> safety (trip) -> latency line -> physics step
  (RK4, noise held over the step) -> on-board Fourier correlation -> ring buffer.

Random numbers are drawn by the caller (numpy Generator) and passed in, so a run
is reproducible bit for bit whatever the chunking.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..physics.rhs import flutter_deriv, oscillator_deriv
from .layout import (
    CFG_CLAMP, CFG_FILTER_HZ, CFG_FREQ, CFG_KD, CFG_KP, CFG_NAVG, CFG_PARAM,
    CFG_PHASE_MODE, CFG_TARGET, CFG_TRIP, CH_CONTROL, CH_EXCITATION, CH_RESPONSE,
    CH_SECOND, DELAY_MAX, FAULT_DIVERGED, FAULT_TRIP, FW_EDF, FW_EF, FW_EXC,
    FW_PERIOD_T, FW_TGT, FW_TGTD, FW_TH_EST, FW_TH_FORCE, FW_TH_PREV, FW_TH_UNWRAP,
    FW_U, FW_XM, HIST_MAX, IC_ARMED, IC_DELAY_POS, IC_FAULT, IC_HIST_N,
    IC_HIST_POS, IC_PERIODS, IC_SAT, IC_SEQ, IC_TRIPS, NCH, NCOEF, NHARM,
    REC_CONTROL, REC_PARAM, REC_PHASE, REC_Q2, REC_Q2D, REC_SEQ, REC_TARGET,
    REC_X, REC_XD, RIG_DT, CFG_RING_DEC, IC_RING_HEAD, RIG_FS, RIG_KIND, RIG_LATENCY, RIG_LSB, RIG_MASS,
    RIG_NOISE, RIG_PARAM_FS, RIG_SAT, RIG_SIGMA, RIG_U_FS, RING_CAP,
)

TWO_PI = 2.0 * math.pi
# Beyond these the rig is treated as broken (a real structure would be).
DIVERGED_X = 10.0


@njit(cache=True, inline="always")
def _quantise(v, lsb, fs):
    if v > fs:
        v = fs
    elif v < -fs:
        v = -fs
    if lsb > 0.0:
        return math.floor(v / lsb + 0.5) * lsb
    return v


@njit(cache=True, inline="always")
def _to_i16(v, fs):
    c = math.floor(v / fs * 32767.0 + 0.5)
    if c > 32767.0:
        c = 32767.0
    elif c < -32767.0:
        c = -32767.0
    return np.uint16(np.int64(c) & 0xFFFF)


@njit(cache=True)
def _deriv(kind, y, dy, u_exc, f_ext, m_ext, phys, eff, mass):
    if kind == 0:
        flutter_deriv(y, dy, u_exc + f_ext, m_ext, phys, eff)
    else:
        oscillator_deriv(y, dy, u_exc, f_ext, phys, eff, mass)


@njit(cache=True)
def _rk4(kind, y, dt, u_exc, f_ext, m_ext, phys, eff, mass, k1, k2, k3, k4, tmp):
    n = y.shape[0]
    _deriv(kind, y, k1, u_exc, f_ext, m_ext, phys, eff, mass)
    for j in range(n):
        tmp[j] = y[j] + 0.5 * dt * k1[j]
    _deriv(kind, tmp, k2, u_exc, f_ext, m_ext, phys, eff, mass)
    for j in range(n):
        tmp[j] = y[j] + 0.5 * dt * k2[j]
    _deriv(kind, tmp, k3, u_exc, f_ext, m_ext, phys, eff, mass)
    for j in range(n):
        tmp[j] = y[j] + dt * k3[j]
    _deriv(kind, tmp, k4, u_exc, f_ext, m_ext, phys, eff, mass)
    for j in range(n):
        y[j] += dt / 6.0 * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k4[j])


@njit(cache=True, inline="always")
def _accumulate(acc, cosk, sink, w, sig0, sig1, sig2, sig3):
    for k in range(NCOEF):
        if k == 0:
            wk = w
        elif k <= NHARM:
            wk = cosk[k] * w
        else:
            wk = sink[k - NHARM] * w
        acc[CH_RESPONSE, k] += sig0 * wk
        acc[CH_CONTROL, k] += sig1 * wk
        acc[CH_EXCITATION, k] += sig2 * wk
        acc[CH_SECOND, k] += sig3 * wk


@njit(cache=True)
def _close_period(fw, ic, cfg, acc, hist, fhist, fmean, fvar, cmean, cvar, dtheta_sum):
    """One estimator period is complete: turn correlations into coefficients and
    update the running mean/variance over the last N periods."""
    pos = ic[IC_HIST_POS]
    for c in range(NCH):
        hist[c, pos, 0] = acc[c, 0] / dtheta_sum
        for k in range(1, NCOEF):
            hist[c, pos, k] = 2.0 * acc[c, k] / dtheta_sum
            acc[c, k] = 0.0
        acc[c, 0] = 0.0
    period = fw[FW_PERIOD_T]
    fhist[pos] = 1.0 / period if period > 0.0 else 0.0
    ic[IC_HIST_POS] = (pos + 1) % HIST_MAX
    if ic[IC_HIST_N] < HIST_MAX:
        ic[IC_HIST_N] += 1
    ic[IC_PERIODS] += 1
    navg = int(cfg[CFG_NAVG])
    n = min(navg, ic[IC_HIST_N])
    for c in range(NCH):
        for k in range(NCOEF):
            s = 0.0
            for i in range(n):
                s += hist[c, (pos - i) % HIST_MAX, k]
            m = s / n
            v = 0.0
            for i in range(n):
                d = hist[c, (pos - i) % HIST_MAX, k] - m
                v += d * d
            cmean[c, k] = m
            cvar[c, k] = v / (n - 1) if n > 1 else 0.0
    s = 0.0
    for i in range(n):
        s += fhist[(pos - i) % HIST_MAX]
    m = s / n
    v = 0.0
    for i in range(n):
        d = fhist[(pos - i) % HIST_MAX] - m
        v += d * d
    fmean[0] = m
    fvar[0] = v / (n - 1) if n > 1 else 0.0
    fw[FW_PERIOD_T] = 0.0


@njit(cache=True, nogil=True)
def advance(nsteps, y, fw, ic, cfg, rig, phys, eff, noise, ext, acc, hist, fhist,
            fmean, fvar, cmean, cvar, delay, ring):
    """Advance the board nsteps samples. noise: (nsteps, 5) standard normals
    (process, then the four sensors). ext: external (plugin) generalised force per
    DoF, held over the call. Returns the number of periods completed."""
    kind = int(rig[RIG_KIND])
    dt = rig[RIG_DT]
    sat = rig[RIG_SAT]
    sigma = rig[RIG_SIGMA]
    mass = rig[RIG_MASS]
    latency = int(rig[RIG_LATENCY])
    n = y.shape[0]
    k1 = np.empty(n)
    k2 = np.empty(n)
    k3 = np.empty(n)
    k4 = np.empty(n)
    tmp = np.empty(n)
    meas = np.empty(4)
    cosk = np.empty(NHARM + 1)
    sink = np.empty(NHARM + 1)
    clamp = min(cfg[CFG_CLAMP], sat)
    omega = TWO_PI * cfg[CFG_FREQ]
    fc = cfg[CFG_FILTER_HZ]
    alpha_f = 1.0 - math.exp(-TWO_PI * fc * dt) if fc > 0.0 else 1.0
    locked = cfg[CFG_PHASE_MODE] > 0.5
    param = cfg[CFG_PARAM]
    ring_dec = max(1, int(cfg[CFG_RING_DEC]))
    completed = 0
    sqdt = math.sqrt(dt)
    for s in range(nsteps):
        # ---- measure -------------------------------------------------------
        if kind == 0:
            tru0, tru1, tru2, tru3 = y[0], y[3], y[1], y[4]
        else:
            tru0, tru1, tru2, tru3 = y[0], y[1], 0.0, 0.0
        meas[0] = _quantise(tru0 + rig[RIG_NOISE] * noise[s, 1], rig[RIG_LSB], rig[RIG_FS])
        meas[1] = _quantise(tru1 + rig[RIG_NOISE + 1] * noise[s, 2], rig[RIG_LSB + 1], rig[RIG_FS + 1])
        if kind == 0:
            meas[2] = _quantise(tru2 + rig[RIG_NOISE + 2] * noise[s, 3], rig[RIG_LSB + 2], rig[RIG_FS + 2])
            meas[3] = _quantise(tru3 + rig[RIG_NOISE + 3] * noise[s, 4], rig[RIG_LSB + 3], rig[RIG_FS + 3])
        else:
            meas[2] = 0.0
            meas[3] = 0.0
        for j in range(4):
            fw[FW_XM + j] = meas[j]
        x = meas[0]
        xd = meas[1]
        # ---- phase -----------------------------------------------------------
        th_force = fw[FW_TH_FORCE]
        if locked:
            # phase of the response itself (paper, appendix B): x - a0 ~ A cos(theta)
            th = math.atan2(-xd, omega * (x - cfg[CFG_TARGET]))
            if th < 0.0:
                th += TWO_PI
        else:
            th = th_force
        fw[FW_TH_EST] = th
        # ---- target ------------------------------------------------------------
        c1 = math.cos(th)
        s1 = math.sin(th)
        cosk[0] = 1.0
        sink[0] = 0.0
        for k in range(1, NHARM + 1):
            cosk[k] = cosk[k - 1] * c1 - sink[k - 1] * s1
            sink[k] = sink[k - 1] * c1 + cosk[k - 1] * s1
        tgt = cfg[CFG_TARGET]
        tgtd = 0.0
        for k in range(1, NHARM + 1):
            ak = cfg[CFG_TARGET + k]
            bk = cfg[CFG_TARGET + NHARM + k]
            tgt += ak * cosk[k] + bk * sink[k]
            tgtd += omega * k * (bk * cosk[k] - ak * sink[k])
        fw[FW_TGT] = tgt
        fw[FW_TGTD] = tgtd
        # ---- control law -------------------------------------------------------
        e = tgt - x
        ed = tgtd - xd
        fw[FW_EF] += alpha_f * (e - fw[FW_EF])
        fw[FW_EDF] += alpha_f * (ed - fw[FW_EDF])
        u = 0.0
        if ic[IC_ARMED] == 1 and ic[IC_FAULT] == 0:
            u = cfg[CFG_KP] * fw[FW_EF] + cfg[CFG_KD] * fw[FW_EDF]
            if u > clamp:
                u = clamp
                ic[IC_SAT] += 1
            elif u < -clamp:
                u = -clamp
                ic[IC_SAT] += 1
        # ---- safety: amplitude trip (latched) ------------------------------------
        # the trip guards the output stage: it acts while armed (disarmed, there is
        # no output to cut and the structure may ring freely)
        if abs(x) > cfg[CFG_TRIP] and ic[IC_FAULT] == 0 and ic[IC_ARMED] == 1:
            ic[IC_FAULT] = FAULT_TRIP
            ic[IC_ARMED] = 0
            ic[IC_TRIPS] += 1
            u = 0.0
        fw[FW_U] = u
        # ---- actuator latency --------------------------------------------------
        dp = ic[IC_DELAY_POS]
        delay[dp] = u
        u_act = delay[(dp - latency) % DELAY_MAX]
        ic[IC_DELAY_POS] = (dp + 1) % DELAY_MAX
        # ---- physics -----------------------------------------------------------
        if kind == 0:
            exc = u_act
            m_noise = sigma * noise[s, 0] / sqdt   # white moment: sigma dW over the step
            _rk4(kind, y, dt, u_act, ext[0], ext[1] + m_noise, phys, eff, mass, k1, k2, k3, k4, tmp)
        else:
            exc = param * math.cos(th_force) + u_act
            # process noise on the oscillator: random force per unit mass
            _rk4(kind, y, dt, exc, ext[0] + mass * sigma * noise[s, 0] / sqdt, 0.0, phys,
                 eff, mass, k1, k2, k3, k4, tmp)
        fw[FW_EXC] = exc
        # ---- on-board Fourier correlation ----------------------------------------
        if locked:
            dth = th - fw[FW_TH_PREV]
            if dth > math.pi:
                dth -= TWO_PI
            elif dth < -math.pi:
                dth += TWO_PI
        else:
            dth = omega * dt
        sig0 = x
        sig1 = u
        sig2 = exc
        sig3 = meas[2]
        prev_unwrap = fw[FW_TH_UNWRAP]
        # a period rarely ends on a sample: split the boundary sample's weight between the
        # closing period and the next, so each window spans exactly 2 pi of phase
        w_now = dth
        if dth > 0.0 and prev_unwrap + dth >= TWO_PI:
            w_now = TWO_PI - prev_unwrap
        _accumulate(acc, cosk, sink, w_now, sig0, sig1, sig2, sig3)
        fw[FW_PERIOD_T] += dt * (w_now / dth if dth != 0.0 else 1.0)
        fw[FW_TH_UNWRAP] = prev_unwrap + dth
        fw[FW_TH_PREV] = th
        if fw[FW_TH_UNWRAP] >= TWO_PI:
            _close_period(fw, ic, cfg, acc, hist, fhist, fmean, fvar, cmean, cvar, TWO_PI)
            fw[FW_TH_UNWRAP] -= TWO_PI
            rest = dth - w_now
            _accumulate(acc, cosk, sink, rest, sig0, sig1, sig2, sig3)
            fw[FW_PERIOD_T] = dt * (rest / dth)
            completed += 1
        elif fw[FW_TH_UNWRAP] < -TWO_PI:
            # running backwards a whole turn (no oscillation): restart the period
            for c in range(NCH):
                for k in range(NCOEF):
                    acc[c, k] = 0.0
            fw[FW_TH_UNWRAP] = 0.0
            fw[FW_PERIOD_T] = 0.0
        # the forcing phase always advances with the forcing frequency
        th_force += omega * dt
        if th_force >= TWO_PI:
            th_force -= TWO_PI
        fw[FW_TH_FORCE] = th_force
        # ---- divergence guard ----------------------------------------------------
        if not (abs(y[0]) < DIVERGED_X) or not np.isfinite(y[1]):
            for j in range(n):
                y[j] = 0.0
            if ic[IC_FAULT] == 0:
                ic[IC_FAULT] = FAULT_DIVERGED
            ic[IC_ARMED] = 0
        # ---- ring buffer -----------------------------------------------------------
        seq = ic[IC_SEQ]
        if seq % ring_dec == 0:
            r = ic[IC_RING_HEAD] % RING_CAP
            ring[r, REC_SEQ] = np.uint16(seq & 0xFFFF)
            ring[r, REC_X] = _to_i16(meas[0], rig[RIG_FS])
            ring[r, REC_XD] = _to_i16(meas[1], rig[RIG_FS + 1])
            ring[r, REC_Q2] = _to_i16(meas[2], rig[RIG_FS + 2])
            ring[r, REC_Q2D] = _to_i16(meas[3], rig[RIG_FS + 3])
            ring[r, REC_TARGET] = _to_i16(tgt, rig[RIG_FS])
            ring[r, REC_CONTROL] = _to_i16(u, rig[RIG_U_FS])
            ring[r, REC_PARAM] = _to_i16(param, rig[RIG_PARAM_FS])
            ring[r, REC_PHASE] = _to_i16(th - math.pi, math.pi)
            ic[IC_RING_HEAD] += 1
        ic[IC_SEQ] = seq + 1
    return completed
