"""Penalties a training loss adds to its data term: small named objects, each with its
own weight, that the losses loop over.

A penalty is ``weight * value(model, points)``; ``points`` are the :class:`Regularity`
points (airspeeds over the traced range, states and shapes of the measured orbits) for the
penalties that need them. Each penalty says which stages of training it acts in and
whether it applies to the aerofoil only; :class:`~ude_fit.training.options.FitOptions`
checks that against the system and the approximator. To add one: subclass
:class:`Penalty`, set ``option`` (its one name, also its command-line flag ``--option``),
write ``value``, and list it in :data:`PENALTIES`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._fourier import amplitude, harmonics
from .._systems import AirspeedWindow
from ..data.estimates import unstable_amplitude_line
from ..models import harmonic_balance
from ..models.mechanistic import Drive
from ..models.ude import UDE
from .identify import TrainingData


ALL_STAGES = ("equation", "trajectory", "periodic")


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
    # for the rest-stability penalty: the measured unstable orbits' own airspeeds, where the
    # equilibrium each of them surrounds is stable (the grid V may stop short of the highest)
    surrounded_V: jax.Array | None = None
    # for the unstable-branch penalty: the unstable branch the data shows, as heave
    # amplitudes (m), increasing from near the Hopf point (:func:`unstable_band`)
    band_amp: jax.Array | None = None


def regularity_points(data: TrainingData, n_v: int = 32, per_orbit: int = 8) -> Regularity:
    """The penalty points for ``data``: airspeeds across the range the diagram is traced
    over (see ``_fit.diagram_ranges``), states at ``per_orbit`` phases of every orbit."""
    P = np.asarray(data.drive.param, float)
    window = AirspeedWindow.of(P)
    span = window.span
    V = np.linspace(window.low, window.high, n_v)
    ys = np.asarray(data.ys)
    step = max(1, ys.shape[1] // per_orbit)
    # an unstable limit cycle surrounds a stable equilibrium (it is the boundary of its
    # basin): the equilibrium is stable up to the highest airspeed of one
    lab = np.asarray(data.label)
    v_stable = P[lab < 0].max() if np.any(lab < 0) else -np.inf
    # first-harmonic heave amplitude of each orbit, to scale its shape to unit amplitude
    amp = amplitude(harmonics(ys[:, :, 0].T, 1))
    a_grid = np.linspace(0.04, 1.3, 16) * amp.max()
    v_hopf = _hopf_from_unstable(P, amp, lab)
    # 16 samples per shape: the cycle mean of q' (7 harmonics) times the force is exact
    # while the force has nothing above the 9th harmonic
    every = max(1, ys.shape[1] // 16)
    band = unstable_band(P, amp, lab)
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
                                           span / 4)),
                      jnp.asarray(np.unique(P[lab < 0])) if np.any(lab < 0) else None,
                      None if band is None else jnp.asarray(band))


def unstable_band(P, amp, lab, points: int = 24):
    """The heave amplitudes (points,), increasing, of the unstable branch the data shows,
    where every orbit of the model must be unstable, followed from the model's Hopf point;
    None where the data shows no such stretch.

    The stretch is read from the unstable orbits in order of amplitude, from the smallest up,
    as long as the airspeed falls from one to the next (as it does on an unstable branch
    from a subcritical Hopf point with one fold; where it rises, the points' scatter decides
    their order and the data says nothing of the branch between them) and no stable orbit
    lies between two of them in amplitude. It starts at 5 % of the smallest, near the Hopf
    point; where a stable orbit is smaller than the smallest unstable one the branch from
    the Hopf point is not the data's unstable one and there is no stretch."""
    unstable = np.nonzero(lab < 0)[0]
    if unstable.size == 0:
        return None
    unstable = unstable[np.argsort(amp[unstable])]
    stable_amps = amp[lab > 0]
    if np.any(stable_amps < amp[unstable[0]]):
        return None
    run = [unstable[0]]
    for j in unstable[1:]:
        i = run[-1]
        if P[j] >= P[i] or np.any((stable_amps > amp[i]) & (stable_amps < amp[j])):
            break
        run.append(j)
    return np.linspace(0.05 * amp[run[0]], amp[run[-1]], points)


def hopf_from_unstable(data: TrainingData) -> float:
    """The Hopf airspeed the training data's unstable orbits extrapolate to (+inf where
    they cannot say)."""
    ys = np.asarray(data.ys)
    return _hopf_from_unstable(np.asarray(data.drive.param, float),
                               amplitude(harmonics(ys[:, :, 0].T, 1)), np.asarray(data.label))


def _hopf_from_unstable(P, amp, lab) -> float:
    """Where the unstable orbits' amplitude^2, linear in V near a Hopf point, reaches zero
    (as ``_metrics.estimate_from_data``); +inf where the data cannot say (fewer than two
    unstable orbits, or no shrinking trend)."""
    c = unstable_amplitude_line(P[lab < 0], amp[lab < 0])
    return float(-c[1] / c[0]) if c is not None and c[0] < 0 else np.inf


def _work_per_amplitude2(force_at, y_unit, V, dt, amps, n):
    """Net work per cycle over A^2 of the force ``force_at(drive)(y)`` along the
    unit-amplitude orbit shape ``y_unit`` (samples over one period, ``dt`` apart) scaled to
    each amplitude A in ``amps``, at airspeed V: the describing-function energy balance.
    ``force_at`` builds the force once per drive (a rest-free correction's terms at rest
    depend on the airspeed alone: :meth:`UDE.at_drive`)."""
    d = Drive.of(V)
    force = force_at(d)

    def at(a):
        F = jax.vmap(lambda y: force(a * y))(y_unit)
        return jnp.sum(F * y_unit[:, n:2 * n]) * dt / a
    return jax.vmap(at)(amps)


def _aero_work_scale(model: UDE, reg: Regularity):
    """The mechanistic model's aerodynamic damping work on the measured shapes at unit
    amplitude (mean magnitude): the unit the energy penalties are measured in."""
    n = model.mech.n_dof
    B = model.mech.base.aero_damping

    def one(y_unit, V, dt):
        qd = y_unit[:, n:2 * n]
        return jnp.abs(jnp.sum((qd @ B(V).T) * qd) * dt)
    return jax.lax.stop_gradient(jnp.mean(jax.vmap(one)(reg.shapes, reg.shape_V,
                                                         reg.shape_dt)))


@dataclass(frozen=True)
class Penalty:
    """A weighted term of the training loss. Subclasses set ``option`` (the penalty's one
    name), ``stages`` (where it acts), ``aerofoil_only`` and ``needs_points`` (whether
    ``value`` reads the :class:`Regularity` points), and define ``value``."""
    weight: float = 0.0

    option: ClassVar[str] = ""
    help: ClassVar[str] = ""          # the command line's help for --option
    stages: ClassVar[tuple[str, ...]] = ALL_STAGES
    aerofoil_only: ClassVar[bool] = True
    needs_points: ClassVar[bool] = True

    def __post_init__(self):
        w = self.weight
        if isinstance(w, bool) or not isinstance(w, (int, float)) or not math.isfinite(w) \
                or w < 0:
            raise ValueError(f"--{self.option} must be a finite number at least 0, not {w!r}")

    @property
    def tolerance(self) -> float:
        """The value at or below which the penalty's condition counts as met (for the
        hinges with a margin: a shortfall of at most 1 % of the margin everywhere)."""
        margin = getattr(self, "margin", 0.0)
        return (0.01 * margin) ** 2

    def active(self, stage: str) -> bool:
        return bool(self.weight) and stage in self.stages

    def value(self, model: UDE, reg: Regularity | None):
        raise NotImplementedError

    def to_json(self) -> dict:
        return {self.option: self.weight}


def penalty_sum(penalties, stage: str, model: UDE, reg: Regularity | None):
    """The weighted sum of the ``penalties`` that act in ``stage`` (0.0 if none do)."""
    out = 0.0
    for p in penalties:
        if p.active(stage):
            out = out + p.weight * p.value(model, reg)
    return out


@dataclass(frozen=True)
class EnergyShape(Penalty):
    option: ClassVar[str] = "energy-shape"
    help: ClassVar[str] = ('aerofoil: penalty on a correction whose net work per cycle over '
                           'amplitude squared is not concave in amplitude squared (along the '
                           "measured orbits' shapes): at most one unstable and one stable "
                           'orbit per airspeed, against diagrams that snake in amplitude '
                           '(default 0)')

    def value(self, model: UDE, reg: Regularity):
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
        def correction_at(d):
            frozen = model.at_drive(d)
            return lambda y: frozen.correction_force(y, d)

        work = lambda y, V, dt: _work_per_amplitude2(correction_at, y, V, dt,
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


@dataclass(frozen=True)
class EnergyRising(Penalty):
    margin: float = 0.025
    option: ClassVar[str] = "energy-rising"
    help: ClassVar[str] = ('aerofoil: penalty on a model whose net work per cycle over '
                           'amplitude squared (mechanistic forces and correction, along the '
                           "measured orbits' shapes) does not rise with the airspeed, from "
                           'just below the measured airspeeds up: the orbits then lie on one '
                           'curve V(amplitude), against branches that turn back and isolas '
                           '(default 0)')

    def value(self, model: UDE, reg: Regularity):
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
        mech = model.mech.base
        def total_at(d):
            frozen = model.at_drive(d)
            return lambda y: mech.force(y[:n], y[n:2 * n], d) + frozen.correction_force(y, d)
        Vr = reg.rising_V
        # down to 1 % of the largest orbit: the hooks a branch makes near its Hopf point
        amps = jnp.concatenate([jnp.array([0.01, 0.02]) * reg.energy_amps[-1] / 1.3,
                                reg.energy_amps])
        D = jax.vmap(lambda y, dt: jax.vmap(
            lambda v: _work_per_amplitude2(total_at, y, v, dt, amps, n))(Vr))(
            reg.shapes, reg.shape_dt)                          # (orbits, airspeeds, amplitudes)
        # dD/dV over the measured airspeeds' spread, in units of the aerodynamic work
        rise = jnp.diff(D, axis=1) / jnp.diff(Vr)[None, :, None] * reg.v_span / _aero_work_scale(
            model, reg)
        return jnp.mean(jax.nn.relu(self.margin - rise) ** 2)


@dataclass(frozen=True)
class RestStability(Penalty):
    margin: float = 1e-3
    option: ClassVar[str] = "rest-stability"
    help: ClassVar[str] = ('aerofoil: penalty on any growth rate of the equilibrium at the '
                           'airspeeds where the data shows it stable (up to the highest '
                           "unstable orbit's), so the correction cannot move the Hopf point "
                           'below the measured orbits, and on any decay rate beyond the Hopf '
                           'point the shrinking unstable orbits point to (default 0)')

    def value(self, model: UDE, reg: Regularity):
        """Squared hinge on the equilibrium's largest growth rate (over the orbits' angular
        frequency) at the airspeeds where the data says the equilibrium is stable: a correction
        otherwise free there can move the Hopf point far below the measured orbits. Where the
        data points to a Hopf point, the same hinge the other way beyond it."""
        def growth(V):
            # at the equilibrium itself: a correction with a force at rest moves it off y = 0,
            # and the Hopf point is that of the moved equilibrium (Newton from y = 0)
            J = harmonic_balance.rest(model, V)[1]
            return jnp.max(jnp.real(jnp.linalg.eigvals(J))) / reg.omega

        g = jax.vmap(growth)(reg.V)
        r = jax.nn.relu(g + self.margin) ** 2
        hinge, count = jnp.sum(r * reg.rest_stable), jnp.sum(reg.rest_stable)
        if reg.surrounded_V is not None:
            hinge = hinge + jnp.sum(jax.nn.relu(jax.vmap(growth)(reg.surrounded_V)
                                                + self.margin) ** 2)
            count = count + reg.surrounded_V.size
        out = hinge / jnp.maximum(1.0, count)
        if reg.rest_unstable is None:
            return out
        # and beyond the Hopf point the shrinking unstable orbits point to, an unstable one: a
        # correction free there can keep the equilibrium stable past it and turn the unstable
        # branch back before it reaches zero amplitude
        u = jax.nn.relu(self.margin - g) ** 2
        return out + jnp.sum(u * reg.rest_unstable) / jnp.maximum(1.0, jnp.sum(reg.rest_unstable))


@dataclass(frozen=True)
class UnstableBranch(Penalty):
    margin: float = 0.025
    option: ClassVar[str] = "unstable-branch"
    help: ClassVar[str] = ("aerofoil: penalty on a model whose branch's airspeed (its "
                           'one-harmonic balance, followed in amplitude) does not fall as the '
                           'amplitude grows along the unstable branch the data shows (from '
                           "the model's Hopf point up through the unstable orbits that grow "
                           'as the airspeed falls): against a supercritical '
                           'Hopf point and S-bends between the unstable orbits (default 0)')

    def value(self, model: UDE, reg: Regularity):
        """Squared hinge on the model's own branch's slope dV/du along the unstable branch
        the data shows (:func:`unstable_band`), u = (a / a_top)^2 for heave amplitude a and
        a_top the largest orbit's, in units of the measured airspeeds' spread: it must be
        at most ``-margin`` at every amplitude. The branch is the model's one-harmonic
        balance followed in amplitude (:mod:`ude_fit.models.harmonic_balance`); amplitudes
        where it does not converge are left out.

        Why: where the work per cycle grows with the airspeed (the energy-rising condition),
        an orbit is unstable exactly where the branch's airspeed falls as its amplitude
        grows. The data's unstable orbits, from the Hopf point up, say it falls all along
        that stretch; a stretch where it rises is a stable piece between two folds (an S the
        points are too far apart to show), and a rise from zero amplitude is a supercritical
        Hopf point. In u the slope stays finite at the Hopf point (V - V_H is linear in a^2
        there), so the smallest amplitudes count as much as the others."""
        if reg.band_amp is None:
            return jnp.asarray(0.0)
        # the model's hidden states (if any) are scaled as the heave
        scale = jnp.concatenate([reg.y_scale, jnp.full(model.n_state - reg.y_scale.size,
                                                       reg.y_scale[0])])
        fixed = harmonic_balance.held(model)
        z0 = harmonic_balance.hopf_start(fixed, reg.V, reg.band_amp[0])
        zs, ok = harmonic_balance.follow(fixed, reg.band_amp, z0, scale)
        zs = jax.lax.stop_gradient(zs)
        dV_da = harmonic_balance.airspeed_slopes(model, zs, reg.band_amp, scale)
        a_top = reg.energy_amps[-1] / 1.3
        slope = dV_da * a_top ** 2 / (2.0 * reg.band_amp) / reg.v_span
        hinge = jnp.where(ok, jax.nn.relu(jnp.where(ok, slope, 0.0) + self.margin) ** 2, 0.0)
        return jnp.sum(hinge) / jnp.maximum(1.0, jnp.sum(ok))


@dataclass(frozen=True)
class EquilibriumPenalty(Penalty):
    option: ClassVar[str] = "equilibrium-penalty"
    help: ClassVar[str] = ("aerofoil: penalty on the correction's value and slope at the "
                           'equilibrium over the airspeed range, which holds the Hopf point '
                           '(default 0)')

    def value(self, model: UDE, reg: Regularity):
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


@dataclass(frozen=True)
class SmoothnessPenalty(Penalty):
    option: ClassVar[str] = "smoothness-penalty"
    help: ClassVar[str] = ("aerofoil: penalty on the correction's curvature in airspeed and "
                           'amplitude, against diagrams that snake (default 0)')

    def value(self, model: UDE, reg: Regularity):
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


@dataclass(frozen=True)
class WeightDecay(Penalty):
    """Periodic training: the mean square of the network's weight matrices (not biases),
    which keeps the correction smooth between the measured orbits."""
    option: ClassVar[str] = "weight-decay"
    help: ClassVar[str] = ('periodic training: penalty on the mean square network weight, for '
                           'smoother corrections on few noisy points (default 0)')
    stages: ClassVar[tuple[str, ...]] = ("periodic",)
    aerofoil_only: ClassVar[bool] = False
    needs_points: ClassVar[bool] = False

    def value(self, model: UDE, reg: Regularity | None):
        mats = [x for x in jax.tree_util.tree_leaves(eqx.filter(model.correction.mlp,
                                                                 eqx.is_inexact_array))
                if x.ndim == 2]
        return sum(jnp.mean(m ** 2) for m in mats) / max(1, len(mats))


# every penalty, in the order the losses add them (the command line's flags come from it)
PENALTIES = (EnergyShape, EnergyRising, RestStability, UnstableBranch, EquilibriumPenalty,
             SmoothnessPenalty, WeightDecay)

# the conditions ``--constraint-rounds`` enforces (training.rounds.enforce_constraints): both
# hold on the physics' picture (one branch V(A), an equilibrium stable where the data shows it),
# both are hinges that vanish there, so a fit that meets them is not touched;
# ``--constrain-unstable-branch`` adds UnstableBranch (the same kind of condition, off by
# default: measured in docs/experiments.md, thirtieth session)
CONSTRAINTS = (EnergyRising, RestStability)


def constraints_for(cfg) -> tuple[Penalty, ...]:
    """The constraints, each at weight 1 (the enforcement sets its own weights)."""
    if not cfg.constraint_rounds:
        return ()
    kinds = CONSTRAINTS + ((UnstableBranch,) if cfg.constrain_unstable_branch else ())
    return tuple(kind(1.0) for kind in kinds)
