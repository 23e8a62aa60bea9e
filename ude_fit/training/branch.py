"""Branch rounds (aerofoil): the measured orbits on the branch born at the Hopf point.

The periodic loss asks for a closed model orbit through every measured one, but not that
those orbits lie on one branch: a model can put its stable orbits on an isola while the
branch from the Hopf point runs elsewhere, or let that branch turn back and forth between
the points. Here the model's branch from the Hopf point is parametrised by the first-harmonic
heave amplitude A, the quantity the diagram is read in:

    unknowns u = (y0, T, V),   r(u; A, theta) = [phi_T(y0) - y0,  h'(0),  a1(h) - A] = 0.

Solved on a grid of amplitudes by natural continuation from the Hopf point, so every
solution is on the connected branch by construction. Each solution's airspeed is then a
function of the parameters theta through the implicit function theorem; to first order

    V_k(theta) ~ V_k - w_k . r(u_k; A_k, theta),    w_k = J_k^-T e_V   (J_k = dr/du at u_k),

which costs one RK4 orbit per grid amplitude and no monodromy. The branch term asks of the
curve V(A):
* every measured orbit's airspeed at its amplitude (interpolated on the grid),
* the slope's sign its stability implies (a branch leaving a Hopf point of a stable
  equilibrium: dV/dA < 0 unstable, dV/dA > 0 stable, between folds),
* at most one turning point in V along the grid (one fold: the subcritical picture, or none).
The linearisation holds near the parameters it was taken at, so training goes in rounds:
trace, train with the term, trace again.
"""
from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._fourier import amplitude, harmonics
from .._systems import AEROFOIL, AirspeedWindow
from ..models.equilibria import hopf_point
from ..models.flow import rk4_orbit
from ..models.mechanistic import Drive
from ..models.ude import UDE


def _residual(model: UDE, u, A, su, n: int):
    """r(u; A) in scaled units: periodicity, phase (h'(0) = 0), first-harmonic amplitude."""
    ns = model.n_state
    x = u * su
    y0, T, V = x[:ns], x[ns], x[ns + 1]
    yT, ys = rk4_orbit(model, y0, T, Drive.of(V), n)
    c = harmonics(ys[:, 0], 1)
    a1 = jnp.sqrt(c[1] ** 2 + c[2] ** 2)
    nd = model.mech.n_dof
    return jnp.concatenate([(yT - y0) / su[:ns], y0[nd:nd + 1] / su[nd:nd + 1],
                            jnp.atleast_1d((a1 - A) / su[0])])


@eqx.filter_jit
def _compiled_residual_and_jacobian(model, u, A, su, n: int):
    def f(v):
        r = _residual(model, v, A, su, n)
        return r, r
    return jax.jacfwd(f, has_aux=True)(u)


def _residual_and_jacobian(model, u, A, su, n: int):
    """(dr/du, r) from one forward-mode pass (the orbit integrated once); the amplitude goes
    in as an array, so that one compilation serves every amplitude of a grid."""
    return _compiled_residual_and_jacobian(model, u, jnp.asarray(A, dtype=float), su, n)


class BranchTrace(eqx.Module):
    """The branch from the Hopf point at grid amplitudes (the first ``reached`` of them),
    with the sensitivity vectors of the airspeed, and where the measured points fall."""
    u: jax.Array          # (k, ns + 2) scaled unknowns of every solved grid point
    amps: jax.Array       # (k,) grid amplitudes (m)
    w: jax.Array          # (k, ns + 2) airspeed sensitivity: V_k(theta) ~ V_k - w_k . r
    V: jax.Array          # (k,) airspeeds at the trace
    su: jax.Array         # (ns + 2,) scales of the unknowns
    left: jax.Array       # (m,) grid index below each measured point's amplitude
    frac: jax.Array       # (m,) its position between that grid point and the next
    reach: jax.Array      # (m,) 1.0 where the point's amplitude lies within the solved grid
    # where the branch turns back in amplitude before the grid's end: a solution next to the
    # turning point, its amplitude, and the left null vector of dr/du there (zeros: no turn)
    turn_u: jax.Array     # (ns + 2,)
    turn_A: jax.Array     # ()
    turn_w: jax.Array     # (ns + 2,)
    n: int = eqx.field(static=True)


@dataclass(frozen=True)
class BranchData:
    """The measured points as the branch term reads them (host side)."""
    amps: np.ndarray      # (m,) first-harmonic heave amplitude of every measured orbit (m)
    V: np.ndarray         # (m,) their airspeeds
    label: np.ndarray     # (m,) +1 stable, -1 unstable, 0 unknown
    v_range: tuple        # where the branch may run
    v_span: float         # the airspeed scale of the measured points (their span, or a tenth
                          # of the largest airspeed where they nearly coincide)
    scales: np.ndarray    # (ns,) typical state magnitudes
    grid: np.ndarray      # amplitudes the branch is solved at

    @classmethod
    def of(cls, data, n_grid: int = 32) -> "BranchData":
        ys = np.asarray(data.ys)
        amps = amplitude(harmonics(ys[:, :, 0].T, 1))
        P = np.asarray(data.drive.param, float)
        window = AirspeedWindow.of(P)     # the diagram's (analysis.diagram.diagram_ranges)
        # dense near the Hopf point, where a hook (a supercritical start turning back) hides
        top = AEROFOIL.amplitude_window
        grid = np.concatenate([[0.01, 0.02, 0.04], np.linspace(0.07, top, n_grid - 3)]) \
            * amps.max()
        return cls(amps, P, np.asarray(data.label, float), (window.low, window.high),
                   window.span,
                   np.asarray(data.y_scale, float) * np.sqrt(2.0), grid)


def branch_order(bd: BranchData) -> np.ndarray:
    """The orbits in the order a branch with at most one fold meets them from the Hopf
    point: the unstable ones (between the Hopf point and the fold), then the stable ones,
    each class in order of airspeed, in the direction in which its amplitudes grow (the sign
    of the slope of a straight line fitted to amplitude against airspeed); orbits of unknown
    stability last, by amplitude. On either side of a single fold the airspeed along the
    branch is monotone and the amplitude need not be: measured orbits scattered in
    amplitude (a smaller orbit between two larger ones in airspeed) are met in order of
    airspeed, so ordering them by amplitude would ask the branch to turn back and forth."""
    index = np.arange(len(bd.amps))
    parts = []
    for label in (-1.0, 1.0):
        mine = index[bd.label == label]
        V, A = bd.V[mine], bd.amps[mine]
        slope = np.polyfit(V, A, 1)[0] if len(V) > 1 and np.ptp(V) > 0 else 0.0
        key = np.sign(slope) * V if slope != 0 else A
        parts.append(mine[np.lexsort((A, key))])
    unknown = index[bd.label == 0]
    parts.append(unknown[np.argsort(bd.amps[unknown], kind="stable")])
    return np.concatenate(parts)


def amplitude_stages(data) -> list[np.ndarray]:
    """Masks over the orbits for a periodic training that grows with the branch: the
    first orbit along a one-fold branch from the Hopf point alone (:func:`branch_order`),
    then one more at a time in that order, up to all but the last (the stage on every orbit
    follows). So each stage asks the branch already fitted to reach one orbit further,
    instead of asking the network for every orbit at once (which it can meet on an isola
    apart from the branch from the Hopf point)."""
    order = branch_order(BranchData.of(data))
    masks = []
    for k in range(1, len(order)):
        m = np.zeros(len(order), bool)
        m[order[:k]] = True
        masks.append(m)
    return masks


def _newton(model, u, A, su, n, maxit=12, tol=1e-10):
    for _ in range(maxit):
        J, r = (np.asarray(x) for x in _residual_and_jacobian(model, jnp.asarray(u), A,
                                                              jnp.asarray(su), n))
        if not (np.all(np.isfinite(J)) and np.all(np.isfinite(r))):
            return None
        try:
            du = np.linalg.solve(J, -r)
        except np.linalg.LinAlgError:
            return None
        u = u + du
        if np.linalg.norm(du) < tol * max(1.0, np.linalg.norm(u)):
            J, _ = _residual_and_jacobian(model, jnp.asarray(u), A, jnp.asarray(su), n)
            return u, np.asarray(J)
    return None


def trace_branch(model: UDE, bd: BranchData, n: int):
    """Natural continuation in amplitude from the Hopf point over ``bd.grid``; stops where a
    Newton solve fails (the branch turns back in amplitude, or leaves the window). Returns
    (trace, grid points solved), or None where the model has no Hopf point in the window or
    the first solves fail."""
    hopf = hopf_point(model, bd.v_range)
    if hopf is None or hopf["omega"] <= 0:
        return None
    ns = model.n_state
    TH = 2 * np.pi / hopf["omega"]
    su = np.concatenate([bd.scales, [TH, max(1.0, hopf["param"])]])
    v = hopf["eigvec"] / hopf["eigvec"][0]
    us, Js, turn = [], [], None
    for k, A in enumerate(bd.grid):
        if k == 0:
            guess = np.concatenate([hopf["y"] + A * np.real(v), [TH, hopf["param"]]]) / su
        elif k == 1:
            guess = us[0]
        else:   # secant prediction
            guess = us[-1] + (us[-1] - us[-2]) * (A - bd.grid[k - 1]) / (
                bd.grid[k - 1] - bd.grid[k - 2])
        sol = _newton(model, guess, float(A), su, n)
        if sol is None:
            if k >= 2:
                turn = _turning_point(model, us[-1], bd.grid[k - 1], float(A), su, n)
            break
        u, J = sol
        T, V = u[ns] * su[ns], u[ns + 1] * su[ns + 1]
        # not stopped at the diagram's window: a branch that runs off below the measured
        # airspeeds must still be seen turning up (or not) to the orbits above it
        if not (V > 0 and TH / 4 < T < 4 * TH):
            break
        us.append(u)
        Js.append(J)
    if len(us) < 2:
        return None
    e = np.zeros(ns + 2)
    e[ns + 1] = su[ns + 1]
    W = np.array([np.linalg.solve(J.T, e) for J in Js])
    k, K = len(us), len(bd.grid)
    g = bd.grid[:k]
    left = np.clip(np.searchsorted(g, bd.amps) - 1, 0, k - 2)
    frac = (bd.amps - g[left]) / (g[left + 1] - g[left])
    reach = (bd.amps >= g[0]) & (bd.amps <= g[-1])
    # padded to the whole grid (one compilation whatever the reach): the unsolved points
    # repeat the last solution with no sensitivity, so their slopes are zero
    U = np.array(us + [us[-1]] * (K - k))
    W = np.concatenate([W, np.zeros((K - k, ns + 2))])
    tu, tA, tw = turn if turn is not None else (us[-1], 0.0, np.zeros(ns + 2))
    return BranchTrace(jnp.asarray(U), jnp.asarray(bd.grid), jnp.asarray(W),
                       jnp.asarray(U[:, ns + 1] * su[ns + 1]), jnp.asarray(su),
                       jnp.asarray(left), jnp.asarray(np.clip(frac, 0.0, 1.0)),
                       jnp.asarray(reach.astype(float)), jnp.asarray(tu),
                       jnp.asarray(float(tA)), jnp.asarray(tw), n), k


def _turning_point(model, u, lo: float, hi: float, su, n, halvings: int = 8):
    """Between a solved amplitude ``lo`` and a failed one ``hi``: bisect for the largest
    amplitude still solved, and there the left singular vector of dr/du of its smallest
    singular value (the left null vector at the turning point, where dr/du is singular).
    Returns (u, A, w) or None where dr/du is not near-singular there (the solve failed for
    another reason)."""
    J = None
    for _ in range(halvings):
        mid = 0.5 * (lo + hi)
        sol = _newton(model, u, mid, su, n)
        if sol is None:
            hi = mid
        else:
            lo, (u, J) = mid, sol
    if J is None:
        J, _ = (np.asarray(x) for x in _residual_and_jacobian(model, jnp.asarray(u), lo,
                                                              jnp.asarray(su), n))
    Us, S, _ = np.linalg.svd(J)
    if S[-1] > 1e-2 * S[0] or abs(Us[-1, -1]) < 1e-8:
        return None
    return u, lo, Us[:, -1]


def branch_airspeeds(model: UDE, tr: BranchTrace):
    """The airspeed of the branch at every grid amplitude for ``model``, to first order from
    the trace (exact for the model traced)."""
    r = jax.vmap(lambda u, A: _residual(model, u, A, tr.su, tr.n))(tr.u, tr.amps)
    return tr.V - jnp.sum(tr.w * r, axis=1)


def one_turn(slope):
    """Squared hinges against more than one turning point: the cheapest split of ``slope``
    into a non-positive run followed by a non-negative one (0 for a branch that falls, then
    rises, or only rises)."""
    up = jnp.cumsum(jnp.concatenate([jnp.zeros(1), jax.nn.relu(slope) ** 2]))
    down = jnp.concatenate([jnp.cumsum((jax.nn.relu(-slope) ** 2)[::-1])[::-1], jnp.zeros(1)])
    return jnp.min(up + down) / slope.size


def branch_terms(model: UDE, tr: BranchTrace, pts_V, pts_label, v_span, a_top):
    """(point, stability, one-turn, reach) terms of the branch, linearised at the trace."""
    V = branch_airspeeds(model, tr)
    # slopes in (A / a_top)^2: finite at the Hopf point, where V - V_H ~ A^2
    e = (tr.amps / a_top) ** 2
    slope = jnp.diff(V) / jnp.diff(e) / v_span
    Vi = V[tr.left] * (1 - tr.frac) + V[tr.left + 1] * tr.frac
    n_reach = jnp.maximum(1.0, jnp.sum(tr.reach))
    point = jnp.sum(tr.reach * ((Vi - pts_V) / v_span) ** 2) / n_reach
    stab = jnp.sum(tr.reach * jax.nn.relu(-pts_label * slope[tr.left]) ** 2) / n_reach
    turns = one_turn(slope)
    # the turning point's amplitude, to first order, pushed out to the grid's end
    rt = _residual(model, tr.turn_u, tr.turn_A, tr.su, tr.n)
    has = jnp.abs(tr.turn_w[-1]) > 0
    A_t = tr.turn_A + tr.su[0] * jnp.dot(tr.turn_w, rt) / jnp.where(has, tr.turn_w[-1], 1.0)
    # (to the largest measured orbit: the branch must hold every point)
    reach = jnp.where(has, jax.nn.relu(1.0 - A_t / a_top) ** 2, 0.0)
    return point, stab, turns, reach
