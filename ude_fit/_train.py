"""Training the correction of a UDE: pure loss functions and the optimiser loop.

Three losses, used in this order by :func:`train_ude`:

* ``equation``: the correction against the residual force the mechanistic model
  leaves on every sample of the averaged orbits (no simulation; a fast start).
* ``trajectory`` (the paper's): integrate the UDE over one period from each
  measured initial state (diffrax, classical RK4 steps, checkpointed reverse mode)
  and compare the states at the measured phases.
* ``periodic`` (beyond the paper): every orbit gets its own initial state and,
  for the autonomous aerofoil, its own period as unknowns; the loss asks for a
  *closed* model orbit that matches the measured one, with the stability the
  data says it has. Stability enters through the sign of the characteristic
  polynomial of the monodromy matrix at 1 (for the aerofoil with its trivial
  multiplier factored out), which changes sign exactly when a real multiplier
  crosses 1, as it does at a fold: smooth and with no eigen-decomposition.

Optimisation: Adam, then L-BFGS (optax), all float64. Losses are module-level
functions of (trainable, static, data), compiled once per problem structure and
shared by every random start.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from ._flow import diffrax_samples, harmonics, rk4_orbit
from ._identify import TrainingData, residual_forces
from ._metrics import unstable_amplitude_line
from ._models import UDE, Drive, MLPCorrection, PolynomialParamCorrection, feature_scaling


class Diverged(RuntimeError):
    """Training produced a non-finite loss; the start is dropped."""


@dataclass(frozen=True)
class TrainConfig:
    """Training settings. A field left at None takes its system's default
    (:data:`SYSTEM_DEFAULTS`, applied by :meth:`for_system`)."""
    width: int = 12
    depth: int = 2
    equation_steps: int | None = None         # Adam steps on the equation loss
    equation_lbfgs_steps: int | None = None   # L-BFGS steps on the equation loss
    adam_steps: int | None = None             # Adam steps on the trajectory/periodic loss
    lbfgs_steps: int | None = None            # L-BFGS steps on the trajectory/periodic loss
    learning_rate: float = 3e-3
    substeps: int | None = None  # RK4 steps between two samples of the orbit
    closure_weight: float = 10.0
    stability_weight: float = 10.0
    stability_margin: float = 0.02
    init_scale: float = 1e-2
    weight_decay: float = 0.0    # periodic training: penalty on the mean square NN weight
    # aerofoil only (see _equilibrium_penalty, _smoothness_penalty): penalties on the
    # correction's value and slope at the equilibrium, and on its curvature in V and amplitude
    linear_weight: float | None = None
    smooth_weight: float | None = None
    param_scale: float = 1.0     # the parameter input is standardised by this times its spread
    rest_weight: float = 0.0     # aerofoil: the equilibrium stable where the data says so
    energy_weight: float = 0.0   # aerofoil: net work per cycle / A^2 concave in A^2
    rising_weight: float = 0.0   # aerofoil: the whole model's net work per cycle / A^2 rising in V
    # how the NN correction depends on the parameter: "input" (a network input like the
    # states) or "polynomial" (a polynomial of param_degree in it, state-dependent
    # coefficients; PolynomialParamCorrection)
    param_dependence: str = "input"
    param_degree: int = 2

    def for_system(self, system: str) -> "TrainConfig":
        """This configuration with every None field set to ``system``'s default."""
        if system not in SYSTEM_DEFAULTS:
            raise ValueError(f"unknown system {system!r} (flutter or oscillator)")
        cfg = dataclasses.replace(self, **{k: v for k, v in SYSTEM_DEFAULTS[system].items()
                                           if getattr(self, k) is None})
        if cfg.param_dependence not in PARAM_DEPENDENCE:
            raise ValueError(f"param_dependence must be input or polynomial, not "
                             f"{cfg.param_dependence!r}")
        if cfg.param_degree < 1:
            raise ValueError(f"param_degree must be at least 1, not {cfg.param_degree}")
        if cfg.equation_lbfgs_steps is None:
            cfg = dataclasses.replace(cfg, equation_lbfgs_steps=cfg.lbfgs_steps)
        return cfg


PARAM_DEPENDENCE = ("input", "polynomial")

# Per-system defaults. The forced oscillator's orbits are smooth enough at 64 RK4 steps per
# period (2 per sample; amplitude within 1e-5 of the converged orbit up to 10 mm), which
# makes its shooting losses 3x cheaper; its correction is cheap to fit to the equation
# residual, and that first stage decides most of the final quality, so it gets more steps.
SYSTEM_DEFAULTS = {
    "flutter": dict(equation_steps=1500, adam_steps=300, lbfgs_steps=100, substeps=4,
                    linear_weight=0.0, smooth_weight=0.0),
    "oscillator": dict(equation_steps=4000, equation_lbfgs_steps=1000, adam_steps=300,
                       lbfgs_steps=100, substeps=2, linear_weight=0.0, smooth_weight=0.0),
}


def _trainable_spec(correction):
    spec = jax.tree_util.tree_map(lambda _: False, correction)
    return eqx.tree_at(lambda c: c.mlp, spec,
                       replace=jax.tree_util.tree_map(eqx.is_inexact_array, correction.mlp))


def new_correction(model: UDE, data: TrainingData, key, cfg: TrainConfig):
    Z, R = residual_forces(model, data)
    sc = feature_scaling(Z, R)
    if cfg.param_scale != 1.0:
        sc = eqx.tree_at(lambda s: s.z_scale, sc, sc.z_scale.at[-1].multiply(cfg.param_scale))
    if cfg.param_dependence == "polynomial":
        return PolynomialParamCorrection(Z.shape[1], R.shape[1], sc, degree=cfg.param_degree,
                                         width=cfg.width, depth=cfg.depth, key=key,
                                         init_scale=cfg.init_scale)
    return MLPCorrection(Z.shape[1], R.shape[1], sc, width=cfg.width,
                         depth=cfg.depth, key=key, init_scale=cfg.init_scale)


# ---------------------------------------------------------------------------------------
# losses
# ---------------------------------------------------------------------------------------

def _equation_loss(params, static, mech, Z, R, reg=None, rw=(0.0, 0.0)):
    corr = eqx.combine(params["corr"], static)
    pred = jax.vmap(corr)(Z)
    loss = jnp.mean(((pred - R) / corr.scaling.out_scale) ** 2)
    return loss + _regularity(UDE(mech, corr), reg, rw)


# ---------------------------------------------------------------------------------------
# regularity of the correction away from the measured orbits
# ---------------------------------------------------------------------------------------

class Regularity(eqx.Module):
    """Where the correction is asked to stay regular (aerofoil): a grid of airspeeds over
    the whole diagram range, the measured states, and the scales that make the penalties
    dimensionless."""
    V: jax.Array          # (m,) airspeeds from below the lowest to beyond the highest measured
    ys: jax.Array         # (k, n_state) states sampled from the measured orbits
    y_scale: jax.Array    # (n_state,)
    v_span: jax.Array     # () the measured airspeeds' spread
    ys_V: jax.Array       # (k,) the airspeed of each state in ys
    rest_stable: jax.Array  # (m,) 1.0 where V holds a stable equilibrium by the data
    omega: jax.Array      # () the measured orbits' mean angular frequency
    # for the energy-shape penalty only:
    shapes: jax.Array | None = None     # (n_orbits, n, n_state) orbits at unit heave amplitude
    shape_V: jax.Array | None = None    # (n_orbits,) their airspeeds
    shape_dt: jax.Array | None = None   # (n_orbits,) time between their samples (s)
    energy_amps: jax.Array | None = None  # (j,) heave amplitudes (m), 4 % to 130 % of the largest
    # for the rest-stability penalty: 1.0 where V is beyond the Hopf point the unstable
    # orbits extrapolate to (their amplitude^2 linear in V, shrinking to zero)
    rest_unstable: jax.Array | None = None
    # for the energy-rising penalty: airspeeds from half a span below the lowest measured
    # one to the end of the traced range
    rising_V: jax.Array | None = None


def regularity_points(data: TrainingData, n_v: int = 32, per_orbit: int = 8) -> Regularity:
    """The penalty points for ``data``: airspeeds across the range the diagram is traced
    over (see ``_fit.diagram_ranges``), states at ``per_orbit`` phases of every orbit."""
    P = np.asarray(data.drive.param, float)
    span = max(float(np.ptp(P)), 0.1 * float(P.max()))
    V = np.linspace(max(0.5, P.min() - 1.5 * span), P.max() + 0.75 * span, n_v)
    ys = np.asarray(data.ys)
    step = max(1, ys.shape[1] // per_orbit)
    # an unstable limit cycle surrounds a stable equilibrium (it is the boundary of its
    # basin): the equilibrium is stable up to the highest airspeed of one
    lab = np.asarray(data.label)
    v_stable = P[lab < 0].max() if np.any(lab < 0) else -np.inf
    # first-harmonic heave amplitude of each orbit, to scale its shape to unit amplitude
    c = harmonics(ys[:, :, 0].T, 1)
    amp = np.hypot(c[1], c[2])
    a_grid = np.linspace(0.04, 1.3, 16) * amp.max()
    v_hopf = _hopf_from_unstable(P, amp, lab)
    # 16 samples per shape: the cycle mean of q' (7 harmonics) times the force is exact
    # while the force has nothing above the 9th harmonic
    every = max(1, ys.shape[1] // 16)
    return Regularity(jnp.asarray(V), jnp.asarray(ys[:, ::step].reshape(-1, ys.shape[-1])),
                      jnp.asarray(data.y_scale), jnp.asarray(span),
                      jnp.asarray(np.repeat(P, len(range(0, ys.shape[1], step)))),
                      jnp.asarray((V <= v_stable).astype(float)),
                      jnp.asarray(float(np.mean(2 * np.pi / np.asarray(data.period)))),
                      jnp.asarray(ys[:, ::every] / amp[:, None, None]), jnp.asarray(P),
                      jnp.asarray(np.asarray(data.period) / ys[:, ::every].shape[1]),
                      jnp.asarray(a_grid),
                      jnp.asarray((V >= v_hopf + 0.1 * span).astype(float)),
                      jnp.asarray(np.arange(P.min() - 0.5 * span, V[-1] + 1e-9,
                                           span / 4)))


def _hopf_from_unstable(P, amp, lab) -> float:
    """Where the unstable orbits' amplitude^2, linear in V near a Hopf point, reaches zero
    (as ``_metrics.estimate_from_data``); +inf where the data cannot say (fewer than two
    unstable orbits, or no shrinking trend)."""
    c = unstable_amplitude_line(P[lab < 0], amp[lab < 0])
    return float(-c[1] / c[0]) if c is not None and c[0] < 0 else np.inf


def _equilibrium_penalty(model: UDE, reg: Regularity):
    """What the correction does to the equilibrium y = 0 and its linearisation, over the
    airspeed range: mean square of U(0; V) and of dU/dy(0; V) y_scale, in units of the
    correction's own force scale. The Hopf point is a property of that linearisation; the
    measured orbits (finite amplitude) hardly constrain it, so without this a network is
    free to move it."""
    out = model.correction.scaling.out_scale
    n = 2 * model.mech.n_dof
    y0 = jnp.zeros(model.n_state)

    def one(V):
        d = Drive.of(V)
        g = lambda y: model.correction_force(y, d) / out
        u0, J = g(y0), jax.jacfwd(g)(y0)
        return jnp.mean(u0 ** 2) + jnp.mean((J[:, :n] * reg.y_scale[:n]) ** 2)

    return jnp.mean(jax.vmap(one)(reg.V))


def _smoothness_penalty(model: UDE, reg: Regularity):
    """Curvature of the correction along the airspeed and along the amplitude, in units of
    its force scale: mean square second difference of U over the airspeed grid at the
    measured states (as d2U/dV2 v_span^2), plus mean square third difference of U(s y; V)
    over s in [0, 1] between the equilibrium and each measured state y (as d3U/ds3). A
    correction that bends quickly with V makes the branch of orbits snake through the
    measured points; one that bends quickly below the smallest measured orbit puts folds
    and isolas between it and the Hopf point. Third differences leave U ~ s^2 free, which
    with the equilibrium penalty (U(0) = dU/dy(0) = 0) is the smoothest way to reach the
    measured correction."""
    out = model.correction.scaling.out_scale
    dV = reg.V[1] - reg.V[0]
    U = jax.vmap(lambda V: jax.vmap(lambda y: model.correction_force(y, Drive.of(V)))(reg.ys))(
        reg.V) / out                                   # (m, k, n_dof)
    d2 = (U[2:] - 2 * U[1:-1] + U[:-2]) * (reg.v_span / dV) ** 2
    s = jnp.linspace(0.0, 1.0, 6)
    W = jax.vmap(lambda a: jax.vmap(lambda y, V: model.correction_force(a * y, Drive.of(V)))(
        reg.ys, reg.ys_V))(s) / out                   # (6, k, n_dof)
    d3 = (W[3:] - 3 * W[2:-1] + 3 * W[1:-2] - W[:-3]) / (s[1] - s[0]) ** 3
    return jnp.mean(d2 ** 2) + jnp.mean(d3 ** 2)


def _rest_penalty(model: UDE, reg: Regularity, margin: float = 1e-3):
    """Squared hinge on the equilibrium's largest growth rate (over the orbits' angular
    frequency) at the airspeeds where the data says the equilibrium is stable: a correction
    otherwise free there can move the Hopf point far below the measured orbits. Where the
    data points to a Hopf point, the same hinge the other way beyond it."""
    y0 = jnp.zeros(model.n_state)

    def growth(V):
        d = Drive.of(V)
        f = lambda y: model.vector_field(0.0, y, d)
        # at the equilibrium itself: a correction with a force at rest moves it off y = 0,
        # and the Hopf point is that of the moved equilibrium (Newton from y = 0)
        y = y0
        for _ in range(3):
            y = y - jnp.linalg.solve(jax.jacfwd(f)(y), f(y))
        J = jax.jacfwd(f)(y)
        return jnp.max(jnp.real(jnp.linalg.eigvals(J))) / reg.omega

    g = jax.vmap(growth)(reg.V)
    r = jax.nn.relu(g + margin) ** 2
    out = jnp.sum(r * reg.rest_stable) / jnp.maximum(1.0, jnp.sum(reg.rest_stable))
    if reg.rest_unstable is None:
        return out
    # and beyond the Hopf point the shrinking unstable orbits point to, an unstable one: a
    # correction free there can keep the equilibrium stable past it and turn the unstable
    # branch back before it reaches zero amplitude
    u = jax.nn.relu(margin - g) ** 2
    return out + jnp.sum(u * reg.rest_unstable) / jnp.maximum(1.0, jnp.sum(reg.rest_unstable))


def _work_per_amplitude2(force, y_unit, V, dt, amps, n):
    """Net work per cycle over A^2 of ``force(y, drive)`` along the unit-amplitude orbit
    shape ``y_unit`` (samples over one period, ``dt`` apart) scaled to each amplitude A in
    ``amps``, at airspeed V: the describing-function energy balance."""
    d = Drive.of(V)

    def at(a):
        F = jax.vmap(lambda y: force(a * y, d))(y_unit)
        return jnp.sum(F * y_unit[:, n:2 * n]) * dt / a
    return jax.vmap(at)(amps)


def _aero_work_scale(model: UDE, reg: Regularity):
    """The mechanistic model's aerodynamic damping work on the measured shapes at unit
    amplitude (mean magnitude): the unit the energy penalties are measured in."""
    n = model.mech.n_dof
    B = getattr(model.mech, "base", model.mech).aero_damping

    def one(y_unit, V, dt):
        qd = y_unit[:, n:2 * n]
        return jnp.abs(jnp.sum((qd @ B(V).T) * qd) * dt)
    return jax.lax.stop_gradient(jnp.mean(jax.vmap(one)(reg.shapes, reg.shape_V,
                                                         reg.shape_dt)))


def _energy_shape_penalty(model: UDE, reg: Regularity):
    """Against diagrams that snake in amplitude: the correction's net work per cycle along
    each measured orbit's shape scaled to heave amplitude A, over A^2, must be concave in
    A^2 (squared hinge on its second derivative in A^2 over an amplitude grid, in units of
    the mechanistic model's aerodynamic work on the same shapes).

    Why: with D(A^2; V) the net work per cycle over A^2 (the describing-function energy
    balance), orbits sit at the roots of D. The mechanistic model's damping and aerodynamic
    forces make D constant in A^2 and its stiffness does no net work, so the correction
    decides the shape. A D concave in A^2 has at most two roots at each airspeed, an
    unstable orbit and a stable one around it: the subcritical picture with one fold. A
    network that bends D up and down between the measured amplitudes puts orbits at every
    bend, which is what makes a diagram snake and isolas appear."""
    work = lambda y, V, dt: _work_per_amplitude2(model.correction_force, y, V, dt,
                                                 reg.energy_amps, model.mech.n_dof)
    # every measured shape at its own airspeed and across the traced range, where nothing
    # measured holds the correction (isolas grow there)
    Vs = jnp.concatenate([reg.shape_V[:, None],
                          jnp.broadcast_to(reg.V[::4], (reg.shape_V.size, reg.V[::4].size))],
                         axis=1)                                    # (orbits, 1 + m/4)
    D = jax.vmap(lambda y, V, dt: jax.vmap(lambda v: work(y, v, dt))(V))(
        reg.shapes, Vs, reg.shape_dt).reshape(-1, reg.energy_amps.size)
    S = _aero_work_scale(model, reg)
    # second divided differences in u = (A / A_top)^2 on the amplitude grid (uniform in A,
    # not in u, so the small orbits near the Hopf point are resolved too), times 1/16^2.
    # (A grid reaching down to 1 % made the penalty dwell on the smallest amplitudes and
    # loosened the fit to 3-6 % on the wind-tunnel data.)
    u = (reg.energy_amps / reg.energy_amps[-1]) ** 2
    s1 = (D[:, 1:] - D[:, :-1]) / (u[1:] - u[:-1])
    d2 = 2 * (s1[:, 1:] - s1[:, :-1]) / (u[2:] - u[:-2]) / 256.0 / S
    return jnp.mean(jax.nn.relu(d2) ** 2)


def _energy_rising_penalty(model: UDE, reg: Regularity, margin: float = 0.025):
    """Against branches that turn back in airspeed and against isolas: the whole model's
    net work per cycle over A^2 (mechanistic forces and correction) along each measured
    shape must grow with the airspeed, at every amplitude of the grid (from 1 % to 130 % of
    the largest orbit), from half a span below the lowest measured airspeed to the end of
    the traced range, a quarter span apart. Squared hinge on its rise across the measured
    airspeeds' spread, which must be at least ``margin`` of the aerodynamic work scale. A
    refined mechanistic model contributes its base model's forces.

    Why: with D(A^2, V) rising in V, its zero set, where the orbits are, is one curve
    V = g(A^2): a single branch, which cannot close on itself or turn back at one
    amplitude. The measured branch says as much: its stable orbits grow and its unstable
    ones shrink with V, both of which need dD/dV > 0 there. Far below the flutter speed the
    aerodynamic damping grows with V and D falls (the quasi-steady model's does, on these
    shapes, below about 18 m/s), so the grid starts half a span below the data."""
    n = model.mech.n_dof
    mech = getattr(model.mech, "base", model.mech)
    total = lambda y, d: mech.force(y[:n], y[n:2 * n], d) + model.correction_force(y, d)
    Vr = reg.rising_V
    # down to 1 % of the largest orbit: the hooks a branch makes near its Hopf point
    amps = jnp.concatenate([jnp.array([0.01, 0.02]) * reg.energy_amps[-1] / 1.3,
                            reg.energy_amps])
    D = jax.vmap(lambda y, dt: jax.vmap(
        lambda v: _work_per_amplitude2(total, y, v, dt, amps, n))(Vr))(
        reg.shapes, reg.shape_dt)                          # (orbits, airspeeds, amplitudes)
    # dD/dV over the measured airspeeds' spread, in units of the aerodynamic work
    rise = jnp.diff(D, axis=1) / jnp.diff(Vr)[None, :, None] * reg.v_span / _aero_work_scale(
        model, reg)
    return jnp.mean(jax.nn.relu(margin - rise) ** 2)


def _regularity(model: UDE, reg: Regularity | None, rw):
    w_lin, w_smooth = rw[:2]
    w_rest = rw[2] if len(rw) > 2 else 0.0
    w_energy = rw[3] if len(rw) > 3 else 0.0
    w_rising = rw[4] if len(rw) > 4 else 0.0
    if reg is None:
        return 0.0
    out = 0.0
    if w_energy:
        out = out + w_energy * _energy_shape_penalty(model, reg)
    if w_rising:
        out = out + w_rising * _energy_rising_penalty(model, reg)
    if w_rest:
        out = out + w_rest * _rest_penalty(model, reg)
    if w_lin:
        out = out + w_lin * _equilibrium_penalty(model, reg)
    if w_smooth:
        out = out + w_smooth * _smoothness_penalty(model, reg)
    return out


def _simulate_with_monodromy(model, y0, T, drive, n, sub):
    """One pass of forward-mode autodiff: end state, samples and the monodromy matrix
    (the tangent integration rides along with the primal one, so the orbit is
    integrated once)."""
    def flow(y):
        yT, ys = rk4_orbit(model, y, T, drive, n * sub)
        return yT, (yT, ys)
    M, (yT, ys) = jax.jacfwd(flow, has_aux=True)(y0)
    return yT, ys[::sub], M


def _stability_indicator(system: str, M):
    """Positive for a stable orbit, negative once a real multiplier passes 1."""
    A = jnp.eye(M.shape[0]) - M
    if system == "flutter":
        # d/dlambda det(lambda I - M) at 1 = sum of the principal (n-1)-minors of I - M;
        # it equals prod over the non-trivial multipliers of (1 - mu).
        k = A.shape[0]
        minors = [jnp.linalg.det(jnp.delete(jnp.delete(A, i, 0), i, 1)) for i in range(k)]
        return sum(minors)
    return jnp.linalg.det(A)


def _trajectory_loss(params, static, mech, data: TrainingData, sub: int, reg=None,
                     rw=(0.0, 0.0)):
    model = UDE(mech, eqx.combine(params["corr"], static))
    return _trajectory_error(model, data, sub) + _regularity(model, reg, rw)


def _trajectory_error(model, data: TrainingData, sub: int):
    n = data.ys.shape[1]

    def one(ys, T, drive):
        sim = diffrax_samples(model, ys[0], T, drive, n, sub)
        return jnp.mean(((sim - ys) / data.y_scale) ** 2)

    return jnp.mean(jax.vmap(one)(data.ys, data.period, data.drive))


def _periodic_objective(model, params, data: TrainingData, sub: int, weights):
    """Closed model orbits through the measured ones, with the measured stability."""
    w_close, w_stab, margin = weights
    n = data.ys.shape[1]
    autonomous = model.system == "flutter"

    def one(ys, y0, T, drive, label):
        yT, sim, M = _simulate_with_monodromy(model, y0, T, drive, n, sub)
        s = _stability_indicator(model.system, M)
        fit = jnp.mean(((sim - ys) / data.y_scale) ** 2)
        close = jnp.sum(((yT - y0) / data.y_scale) ** 2)
        stab = jnp.where(label == 0, 0.0, jax.nn.relu(margin - label * s) ** 2)
        return fit + w_close * close + w_stab * stab

    y0 = data.ys[:, 0, :] + params["dy0"] * data.y_scale
    T = data.period * (1.0 + params["dT"]) if autonomous else data.period
    return jnp.mean(jax.vmap(one)(data.ys, y0, T, data.drive, data.label))


def _weight_penalty(corr_params):
    """Mean square of the network's weight matrices (not biases): weight decay, which keeps
    the correction smooth between the measured orbits."""
    mats = [x for x in jax.tree_util.tree_leaves(corr_params)
            if isinstance(x, jax.Array) and x.ndim == 2]
    return sum(jnp.mean(m ** 2) for m in mats) / max(1, len(mats))


def _periodic_loss(params, static, mech, data: TrainingData, sub: int, weights, reg=None):
    model = UDE(mech, eqx.combine(params["corr"], static))
    loss = _periodic_objective(model, params, data, sub, weights[:3])
    return (loss + weights[3] * _weight_penalty(params["corr"])
            + _regularity(model, reg, weights[4:8]))


def _mech_leaves(mech):
    """The fitted parameters of a mechanistic model as a tuple of arrays: the base
    model's fitted fields, then each added effect's coefficient vector."""
    base = getattr(mech, "base", mech)
    out = tuple(getattr(base, f) for f in base.fitted)
    if base is not mech:
        out = out + tuple(a.coefficients for a in mech.added)
    return out


def _mech_with(mech, sizes, base, scale, delta):
    flat = base + scale * delta
    vals, i = [], 0
    for shp in sizes:
        k = int(np.prod(shp)) if shp else 1
        vals.append(flat[i:i + k].reshape(shp))
        i += k
    return eqx.tree_at(_mech_leaves, mech, tuple(vals))


def _mech_periodic_loss(params, mech, sizes, base, scale, data, sub, weights):
    model = UDE(_mech_with(mech, sizes, base, scale, params["delta"]))
    return _periodic_objective(model, params, data, sub, weights)


def refine_mechanistic(model: UDE, data: TrainingData, *, cfg: TrainConfig, progress=None):
    """Output-error identification of the mechanistic parameters: the equation-error
    estimate (or any start) refined so that the model has closed orbits through the
    measured ones with the measured stability. Returns (UDE without correction, info).
    ``data`` must carry the model's hidden states, if it has any (``augment``)."""
    cfg = cfg.for_system(model.system)
    mech = model.mech
    leaves = _mech_leaves(mech)
    sizes = tuple(tuple(jnp.shape(x)) for x in leaves)
    base = jnp.concatenate([jnp.ravel(jnp.asarray(x, float)) for x in leaves])
    scale = jnp.where(jnp.abs(base) > 0, jnp.abs(base), 1.0)
    params = {"delta": jnp.zeros(base.size), "dy0": jnp.zeros(data.ys[:, 0, :].shape)}
    if model.system == "flutter":
        params["dT"] = jnp.zeros(data.period.shape)
    weights = (cfg.closure_weight, cfg.stability_weight, cfg.stability_margin)
    params, v = minimize(_mech_periodic_loss, params,
                         (mech, sizes, base, scale, data, cfg.substeps, weights),
                         adam_steps=cfg.adam_steps, lbfgs_steps=cfg.lbfgs_steps,
                         lr=cfg.learning_rate, progress=progress, stage="mechanistic")
    refined = _mech_with(mech, sizes, base, scale, params["delta"])
    return UDE(refined), {"loss": v}


# ---------------------------------------------------------------------------------------
# optimiser loop
# ---------------------------------------------------------------------------------------

_ADAM_CHUNK = 25
_OPTIMISERS: dict = {}


def _adam(lr):
    if ("adam", lr) not in _OPTIMISERS:
        _OPTIMISERS[("adam", lr)] = optax.adam(lr)
    return _OPTIMISERS[("adam", lr)]


def _lbfgs():
    if "lbfgs" not in _OPTIMISERS:
        _OPTIMISERS["lbfgs"] = optax.lbfgs()
    return _OPTIMISERS["lbfgs"]


@eqx.filter_jit
def _adam_chunk(params, state, loss, args, opt):
    def body(carry, _):
        p, s = carry
        val, g = jax.value_and_grad(loss)(p, *args)
        u, s = opt.update(g, s, p)
        return (optax.apply_updates(p, u), s), val
    (params, state), vals = jax.lax.scan(body, (params, state), None, length=_ADAM_CHUNK)
    return params, state, vals[-1]


def _strong_types(tree):
    """The same values without JAX's weak types: optax.lbfgs's fresh state holds weakly
    typed scalars that its first update returns strongly typed, so without this the step
    is compiled twice (several seconds for a shooting loss)."""
    return jax.tree_util.tree_map(
        lambda x: jnp.array(x, dtype=x.dtype) if isinstance(x, jax.Array) else x, tree)


@eqx.filter_jit
def _lbfgs_step(params, state, loss, args, opt):
    f = lambda p: loss(p, *args)
    vg = optax.value_and_grad_from_state(f)
    val, g = vg(params, state=state)
    u, state = opt.update(g, state, params, value=val, grad=g, value_fn=f)
    return optax.apply_updates(params, u), state, val


def minimize(loss, params, args, *, adam_steps: int, lbfgs_steps: int, lr: float,
             progress=None, stage: str = ""):
    """Adam then L-BFGS on ``loss(params, *args)``; raises :class:`Diverged` on NaN."""
    t0 = time.perf_counter()
    val = float("nan")
    if adam_steps > 0:
        opt = _adam(lr)
        state = opt.init(params)
        for done in range(_ADAM_CHUNK, adam_steps + _ADAM_CHUNK, _ADAM_CHUNK):
            params, state, v = _adam_chunk(params, state, loss, args, opt)
            val = float(v)
            if not np.isfinite(val):
                raise Diverged(f"{stage}: loss is not finite at Adam step {done}")
            if progress:
                progress(stage=stage, optimiser="adam", step=min(done, adam_steps),
                         steps=adam_steps, loss=val, elapsed=time.perf_counter() - t0)
    if lbfgs_steps > 0:
        opt = _lbfgs()
        state = _strong_types(opt.init(params))
        best = (np.inf, params)
        for k in range(1, lbfgs_steps + 1):
            params, state, v = _lbfgs_step(params, state, loss, args, opt)
            val = float(v)
            if not np.isfinite(val):
                if np.isfinite(best[0]):
                    params, val = best[1], best[0]
                    break
                raise Diverged(f"{stage}: loss is not finite at L-BFGS step {k}")
            if val < best[0]:
                best = (val, params)
            if progress and (k % 10 == 0 or k == lbfgs_steps):
                progress(stage=stage, optimiser="lbfgs", step=k, steps=lbfgs_steps, loss=val,
                         elapsed=time.perf_counter() - t0)
    return params, val


def train_ude(model: UDE, data: TrainingData, *, key, cfg: TrainConfig, training: str,
              progress=None) -> tuple[UDE, dict]:
    """Fit a fresh MLP correction on top of ``model.mech``; returns (UDE, info)."""
    cfg = cfg.for_system(model.system)
    corr = new_correction(model, data, key, cfg)
    trainable, static = eqx.partition(corr, _trainable_spec(corr))
    mech = model.mech
    info = {"training": training}
    Z, R = residual_forces(UDE(mech), data)
    params = {"corr": trainable}
    rw = (cfg.linear_weight, cfg.smooth_weight, cfg.rest_weight, cfg.energy_weight,
          cfg.rising_weight)
    reg = regularity_points(data) if model.system == "flutter" and any(rw) else None
    params, v = minimize(_equation_loss, params,
                         (static, mech, jnp.asarray(Z), jnp.asarray(R), reg, rw),
                         adam_steps=cfg.equation_steps, lbfgs_steps=cfg.equation_lbfgs_steps,
                         lr=1e-2,
                         progress=progress, stage="equation")
    info["equation_loss"] = v
    if training == "trajectory":
        params, v = minimize(_trajectory_loss, params,
                             (static, mech, data, cfg.substeps, reg, rw),
                             adam_steps=cfg.adam_steps, lbfgs_steps=cfg.lbfgs_steps,
                             lr=cfg.learning_rate, progress=progress, stage="trajectory")
    elif training == "periodic":
        # initial states and periods as scaled offsets from the measured ones, so one
        # Adam step size suits metres, radians and seconds alike
        params = {"corr": params["corr"], "dy0": jnp.zeros(data.ys[:, 0, :].shape)}
        if model.system == "flutter":
            params["dT"] = jnp.zeros(data.period.shape)
        weights = (cfg.closure_weight, cfg.stability_weight, cfg.stability_margin,
                   cfg.weight_decay) + rw
        params, v = minimize(_periodic_loss, params,
                             (static, mech, data, cfg.substeps, weights, reg),
                             adam_steps=cfg.adam_steps, lbfgs_steps=cfg.lbfgs_steps,
                             lr=cfg.learning_rate, progress=progress, stage="periodic")
    elif training != "equation":
        raise ValueError(f"unknown training mode {training!r} (trajectory, periodic, equation)")
    info["final_loss"] = v
    return UDE(mech, eqx.combine(params["corr"], static)), info
