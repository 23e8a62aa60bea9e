"""Monotone rounds (aerofoil, experimental): the branch turns only where the stability does.

A branch of self-excited orbits from a Hopf point of an equilibrium that is stable below it
in the airspeed changes stability at its folds: along the branch, in the first-harmonic
heave amplitude A, the airspeed falls (dV/dA < 0) where the orbits are unstable and rises
where they are stable. Two measured orbits of the same stability, next to each other in
amplitude, are therefore joined by a monotone stretch of the branch, unless the branch folds
twice between them; and above the largest orbit, if it is stable, the branch goes on rising.
The fewest folds the labels allow is the hypothesis here: the data is silent between the
orbits and above them, where the correction's freedom otherwise adds folds (a snake
threading scattered points, a turn just above the largest orbit).

Each stretch is traced from the model's own closed orbit through its lower orbit (the
periodic stage's unknowns) by natural continuation in amplitude, with the residual of
:mod:`.branch`, and each grid airspeed is linearised in the weights by the implicit
function theorem (as the branch rounds do):

    V_k(theta) ~ V_k - w_k . r(u_k; A_k, theta),    w_k = J_k^-T e_V.

The term is the sum over the stretches' grid steps of relu(-d dV / v_span)^2, d = +1 on a
stable stretch, -1 on an unstable one. Unlike the branch rounds, which trace from the Hopf
point and linearise about a branch that can lie far from the orbits, every stretch starts
on an orbit the fit already holds, so the linearisation is taken where the change asked is
small. A stretch whose trace stops (the model's branch turns back in amplitude or ends) is
kept to where it was solved.
"""
from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._systems import AEROFOIL
from ..models.flow import rk4_orbit
from ..models.mechanistic import Drive
from ..models.ude import UDE
from .branch import BranchData, _newton, _residual

# grid amplitudes per stretch between two orbits (both ends included), and above the
# largest orbit
BETWEEN_POINTS = 4
ABOVE_POINTS = 12
# how far above the largest orbit the branch is asked to rise: past the diagram's window
# (the aerofoil's amplitude_window times the largest amplitude), so that a branch
# flattening at the window's edge is seen turning rather than counted as a fold there
ABOVE_REACH = AEROFOIL.amplitude_window * 1.1


@dataclass(frozen=True)
class Stretch:
    """A stretch of the branch the labels say is monotone: traced from orbit ``start`` over
    ``amps``, with the airspeed rising (``direction`` +1) or falling (-1)."""
    start: int
    amps: np.ndarray
    direction: float


def stretches(bd: BranchData) -> list[Stretch]:
    """The monotone stretches the measured orbits' stability implies: between orbits of the
    same stability next to each other in amplitude (among that stability's orbits), and
    above the largest orbit if it is stable. Orbits of unknown stability imply nothing."""
    out = []
    for label in (-1.0, 1.0):
        mine = np.flatnonzero(bd.label == label)
        mine = mine[np.argsort(bd.amps[mine], kind="stable")]
        for i, j in zip(mine[:-1], mine[1:]):
            if bd.amps[j] > bd.amps[i]:
                out.append(Stretch(int(i), np.linspace(bd.amps[i], bd.amps[j],
                                                       BETWEEN_POINTS), label))
    top = int(np.argmax(bd.amps))
    if bd.label[top] > 0:
        out.append(Stretch(top, np.linspace(bd.amps[top], ABOVE_REACH * bd.amps[top],
                                            ABOVE_POINTS), 1.0))
    return out


class MonotoneTrace(eqx.Module):
    """Every stretch's solved grid points, padded to the planned grid (unsolved points
    repeat a solution with no sensitivity), and the steps the term reads."""
    u: jax.Array          # (K, ns + 2) scaled unknowns
    amps: jax.Array       # (K,) grid amplitudes
    w: jax.Array          # (K, ns + 2) airspeed sensitivities
    V: jax.Array          # (K,) traced airspeeds
    su: jax.Array         # (ns + 2,) scales of the unknowns
    lo: jax.Array         # (S,) int: every step's lower grid point (the next is its upper)
    direction: jax.Array  # (S,) +1 rising, -1 falling, 0 not solved
    n: int = eqx.field(static=True)


@eqx.filter_jit
def _orbit_samples(model: UDE, start, T, V, n: int):
    # compiled once: a scan run outside a compiled function is compiled anew at every call,
    # and each compilation keeps its code mapped for the process's life
    return rk4_orbit(model, start, T, Drive.of(V), n)[1]


def _model_orbit_top(model: UDE, data, params, i: int, n: int):
    """The model's closed orbit through measured orbit i (the periodic stage's initial
    state and period), started at the top of its heave swing (h' = 0, the phase condition
    of the residual), as (state, period)."""
    T = float(np.asarray(data.period)[i])
    V = float(data.drive.param[i])
    start = np.asarray(data.ys[i, 0], float)
    if params is not None:
        start = start + np.asarray(params["dy0"][i]) * np.asarray(data.y_scale)
        if "dT" in params:
            T *= 1.0 + float(np.asarray(params["dT"])[i])
        if "dP" in params:
            V += float(data.param_errors.sigma[i] * params["dP"][i])
    ys = np.asarray(_orbit_samples(model, jnp.asarray(start), jnp.asarray(T),
                                   jnp.asarray(V), n))
    return ys[int(np.argmax(ys[:, 0]))], T


def trace_stretches(model: UDE, data, bd: BranchData, plan: list[Stretch], n: int,
                    params=None):
    """Trace every stretch of ``plan`` by natural continuation in amplitude from the model's
    orbit through its start. Returns (trace, grid points solved per stretch), or None where
    no stretch solved two grid points."""
    ns = model.n_state
    V_top = float(np.max(bd.V))
    us, Js, amps, lo, direction, solved, parts = [], [], [], [], [], [], []
    su = None
    for s in plan:
        top, T = _model_orbit_top(model, data, params, s.start, n)
        y0 = np.zeros(ns)
        y0[:min(ns, top.size)] = top[:ns]
        if su is None:   # one scaling for every stretch: the unknowns of one trace
            su = np.concatenate([bd.scales, [T, max(1.0, V_top)]])
        got_u, got_J = [], []
        for k, A in enumerate(s.amps):
            if k == 0:
                guess = np.concatenate([y0, [T, bd.V[s.start]]]) / su
            elif k == 1:
                guess = got_u[-1]
            else:      # secant prediction
                guess = 2 * got_u[-1] - got_u[-2]
            sol = _newton(model, guess, float(A), su, n)
            if sol is None:
                break
            got_u.append(sol[0])
            got_J.append(sol[1])
        solved.append(len(got_u))
        parts.append((s, got_u, got_J))
    if not any(k >= 2 for k in solved):
        return None
    # padded to the planned grid, so that every round's trace has one shape (one
    # compilation): an unsolved point repeats a solved one (its residual stays finite) with
    # no sensitivity and no step
    fill_u, fill_A = next((g[0], float(s.amps[0])) for s, g, _ in parts if g)
    for s, got_u, got_J in parts:
        base = len(us)
        for k in range(len(s.amps)):
            ok = k < len(got_u)
            us.append(got_u[k] if ok else fill_u)
            Js.append(got_J[k] if ok else None)
            amps.append(float(s.amps[k]) if ok else fill_A)
            if k > 0:
                lo.append(base + k - 1)
                direction.append(s.direction if ok else 0.0)
    e = np.zeros(ns + 2)
    e[ns + 1] = su[ns + 1]
    W = np.array([np.linalg.solve(J.T, e) if J is not None else np.zeros(ns + 2) for J in Js])
    U = np.array(us)
    trace = MonotoneTrace(jnp.asarray(U), jnp.asarray(amps), jnp.asarray(W),
                          jnp.asarray(U[:, ns + 1] * su[ns + 1]), jnp.asarray(su),
                          jnp.asarray(np.array(lo, int)),
                          jnp.asarray(np.array(direction, float)), n)
    return trace, solved


def stretch_airspeeds(model: UDE, tr: MonotoneTrace):
    """The airspeed at every grid point of the stretches for ``model``, to first order from
    the trace (exact for the model traced)."""
    r = jax.vmap(lambda u, A: _residual(model, u, A, tr.su, tr.n))(tr.u, tr.amps)
    return tr.V - jnp.sum(tr.w * r, axis=1)


def turning_against(V, tr: MonotoneTrace, v_span):
    """Squared hinges on every step where the airspeed moves against its stretch's
    direction, in units of the measured airspeed span (0 for a branch monotone as the
    labels say)."""
    step = (V[tr.lo + 1] - V[tr.lo]) / v_span
    return jnp.sum(jax.nn.relu(-tr.direction * step) ** 2)


def monotone_term(model: UDE, tr: MonotoneTrace, v_span):
    """The monotone term of ``model``, linearised at the trace."""
    return turning_against(stretch_airspeeds(model, tr), tr, v_span)
