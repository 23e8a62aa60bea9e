"""The periodic objective by collocation: every orbit a truncated Fourier series, the
model's vector field asked to match its derivative, instead of an integration from a free
initial state (the shooting of :func:`.losses.orbit_terms`).

Shooting integrates every orbit over a period at every step, a chain of a few hundred small
operations (four Runge-Kutta stages per step), and that chain, not the arithmetic, is what a
step costs on a CPU. Here the model is evaluated at every phase at once: the whole step is
a handful of batched products. The same terms come out (:class:`.losses.OrbitTerms`): the
misfit of the samples, a *defect* where shooting has its closure, and the stability
indicators of a monodromy matrix, which is the product of the Runge-Kutta propagators of
the variational equation along the series (each propagator a function of the Jacobian at
three phases, so the product needs no sequential integration: it is formed as a balanced
tree of matrix products).

The defect is the vector field's mismatch with the series' derivative, each state over its
scale and the orbit's angular frequency, squared and averaged over the phases, times
(2 pi)^2: a constant relative mismatch delta accumulated over one period moves the end state
by 2 pi delta of the state's scale, which is what the shooting closure measures. So the two
objectives weigh a model that does not close its orbit alike, and the closure weight serves
both.

Where the series come from is the option ``collocation_series``, a plan (:data:`PLANS`):
unknowns of the optimiser beside the model (:class:`FreeSeries`), solved for the model at
every evaluation (:class:`SolvedSeries`, :mod:`.projection`), or, the default, free for the
first steps and solved after them.

What collocation leaves out is the series' truncation: an orbit with harmonics above
:func:`.fourier.harmonics_of`'s is not represented, and the monodromy matrix is a
Runge-Kutta approximation at the sample spacing (one step per sample). It is therefore the
first, long training of a start (:func:`.train._train`), which the shooting objective
finishes, from the initial states and periods collocation found (:func:`shooting_unknowns`).
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..models.amplitude import resolve
from ..models.flow import ordered_product, rk4_propagator
from ..models.ude import UDE
from .fourier import Basis, harmonics_of
from .identify import TrainingData
from .losses import OrbitTerms, objective_of, orbit_offsets
from .options import TrainConfig
from .penalties import penalty_sum
from .projection import OrbitResiduals, solve


class Orbits(eqx.Module):
    """What every orbit's terms take besides its series: period, drive (the parameter
    offset applied), the offset's prior cost and each state's misfit weight."""
    period: jax.Array
    drive: object
    prior: jax.Array
    state_weight: jax.Array

    @staticmethod
    def of(params: dict, data: TrainingData, autonomous: bool) -> "Orbits":
        T = data.period * (1.0 + params["dT"]) if autonomous else data.period
        drive, prior = data.drive, jnp.zeros(data.period.shape)
        if "dP" in params:
            errors = data.param_errors
            drive = eqx.tree_at(lambda d: d.param, drive,
                                drive.param + errors.sigma * params["dP"])
            prior = errors.cost * params["dP"] ** 2
        if autonomous:      # an imposed input is periodic in the orbit's own period
            drive = eqx.tree_at(lambda d: d.omega, drive, 2.0 * jnp.pi / T)
        state_weight = (jnp.ones(data.ys.shape[::2]) if data.state_weight is None
                        else data.state_weight)
        return Orbits(T, drive, prior, state_weight)


class FreeSeries:
    """Every orbit's Fourier coefficients unknowns of the optimiser, as offsets from the
    series through the measured samples, each state over its scale and harmonic j's over
    j: the derivative multiplies harmonic j by j, so a step of one size in every unknown
    moves the orbit's derivative by one size in every harmonic, and an optimiser whose
    steps are scale-free (Adam) does not stir the high harmonics, whose own values are
    small, into a defect larger than the fit it is after. Cheapest per step; on noisy
    orbits the series lag the network (:mod:`.projection`)."""

    def unknowns(self, data: TrainingData, autonomous: bool, lead: tuple = ()) -> dict:
        n_o, n, n_s = data.ys.shape
        return {"dC": jnp.zeros(lead + (n_o, 2 * harmonics_of(n) + 1, n_s)),
                **orbit_offsets(data, autonomous, lead)}

    def series(self, model, params: dict, data: TrainingData, cfg: TrainConfig):
        basis = Basis.of(data.ys.shape[1])
        k = harmonics_of(data.ys.shape[1])
        order = np.concatenate([[1], np.arange(1, k + 1), np.arange(1, k + 1)])[:, None]
        return basis.through(data.ys) + params["dC"] * data.y_scale / order


class SolvedSeries:
    """Every orbit's series solved for the model of the moment (variable projection,
    :mod:`.projection`), from the series through its measured samples: the unknowns are
    the model and the offsets only, and the model's gradient is taken at the solved
    series. A step costs about twice a free one's."""

    def unknowns(self, data: TrainingData, autonomous: bool, lead: tuple = ()) -> dict:
        return orbit_offsets(data, autonomous, lead)

    def series(self, model, params: dict, data: TrainingData, cfg: TrainConfig):
        basis = Basis.of(data.ys.shape[1])
        orbits = Orbits.of(params, data, model.mech.autonomous)

        def one(ys, T, drive, sw):
            res = OrbitResiduals.of(model.at_drive(drive), drive, basis, ys, T, sw,
                                    data.y_scale)
            return solve(res, basis.through(ys), cfg.closure_weight)
        return jax.vmap(one)(data.ys, orbits.period, orbits.drive, orbits.state_weight)


SERIES = {"free": FreeSeries(), "solved": SolvedSeries()}

# The share of the first training's Adam steps that the default plan gives to free series
# before it solves them: from the mechanistic model, whose orbits may lie nowhere near the
# measured ones (lee2020: no limit cycle in the measured range), a series solved for the
# model is a poor place to take the model's gradient (solved series from the start: six of
# 16 starts stuck at 5-22 % on lee2020 seed 2), while free series follow the samples and
# bring the model's orbits near them within the first few hundred steps. One value tried
# (docs/experiments.md, fifty-ninth session), not tuned.
FREE_LEAD = 1.0 / 6.0


class Leg(NamedTuple):
    """One leg of a plan: its series (a key of :data:`SERIES`), its share of the first
    training's Adam steps, and whether the L-BFGS steps are its."""
    series: str
    adam_share: float
    lbfgs: bool


# --collocation-series: how the first training's steps go, leg by leg
PLANS = {"free": (Leg("free", 1.0, True),),
         "solved": (Leg("solved", 1.0, True),),
         "free-then-solved": (Leg("free", FREE_LEAD, False),
                              Leg("solved", 1.0 - FREE_LEAD, True))}


def plan_legs(plan: str, adam_steps: int, lbfgs_steps: int) -> list[tuple[str, int, int]]:
    """(series, Adam steps, L-BFGS steps) of each leg of ``plan``; the legs' Adam steps add
    up to ``adam_steps``."""
    legs, given = [], 0
    for i, leg in enumerate(PLANS[plan]):
        last = i == len(PLANS[plan]) - 1
        adam = adam_steps - given if last else int(round(leg.adam_share * adam_steps))
        given += adam
        legs.append((leg.series, adam, lbfgs_steps if leg.lbfgs else 0))
    return legs


def _series_of(cfg: TrainConfig):
    """The series a plan ends with: the one its objective, and shooting's start, are at."""
    return SERIES[PLANS[cfg.collocation_series][-1].series]


def collocation_unknowns(data: TrainingData, autonomous: bool, lead: tuple = (),
                         series: str = "free") -> dict:
    """Collocation's unknowns besides the model, scaled offsets from the measured values:
    with free series (a key of :data:`SERIES`) every orbit's coefficients, its period where
    the system is autonomous, its parameter where the data says it may be in error."""
    return SERIES[series].unknowns(data, autonomous, lead)


@eqx.filter_jit
def orbit_series(model, params: dict, data: TrainingData, cfg: TrainConfig):
    """(orbits, 2k+1, states) every orbit's series as the collocated objective has it."""
    return _series_of(cfg).series(model, params, data, cfg)


def shooting_unknowns(model, params: dict, data: TrainingData, cfg: TrainConfig) -> dict:
    """The shooting objective's unknowns (:func:`.losses.orbit_unknowns`) where collocation
    left the orbits: each initial state the series' value at phase 0 (a shooting orbit
    starts at the first measured sample's phase), the period and parameter offsets as they
    are."""
    C = orbit_series(model, params, data, cfg)
    y0 = Basis.of(data.ys.shape[1]).at_start(C)
    out = {"dy0": (y0 - data.ys[:, 0, :]) / data.y_scale}
    return {**out, **{k: v for k, v in params.items() if k in ("dT", "dP")}}


def monodromy(J, T):
    """The monodromy matrix from the Jacobians ``J`` (FINE n, s, s) at the fine phases of
    one period ``T``: Runge-Kutta steps two phases long."""
    m = J.shape[0]
    J0, Jm = J[0::2], J[1::2]
    J1 = jnp.roll(J, -2, axis=0)[0::2]          # the period's end is its start
    stages = jnp.stack([J0, Jm, Jm, J1], axis=1)        # (steps, 4, s, s)
    return ordered_product(jax.vmap(rk4_propagator, (0, None))(stages, 2.0 * T / m))


def collocation_terms(model, params, data: TrainingData, cfg: TrainConfig) -> OrbitTerms:
    """Every orbit of ``data`` as its series (the one ``cfg.collocation_series`` ends with):
    its misfit to the measured samples, its defect as the model's orbit (in the closure's
    place), and its stability from the variational equation along it."""
    mech = model.mech
    basis = Basis.of(data.ys.shape[1])
    orbits = Orbits.of(params, data, mech.autonomous)
    C = _series_of(cfg).series(model, params, data, cfg)

    def one(ys, Ck, T, drive, sw):
        res = OrbitResiduals.of(model.at_drive(drive), drive, basis, ys, T, sw, data.y_scale)
        J, f = res.field(Ck)
        M = monodromy(J, T)
        fold = mech.stability_indicator(M)
        secondary = (mech.secondary_indicators(M, fold) if mech.holds_secondary_tests
                     else jnp.full(2, jnp.inf))
        return (jnp.sum(res.misfit(Ck) ** 2), jnp.sum(res.defect(Ck, f) ** 2), fold,
                secondary)

    fit, defect, indicator, secondary = jax.vmap(one)(
        data.ys, C, orbits.period, orbits.drive, orbits.state_weight)
    return OrbitTerms(fit, defect, indicator, secondary, orbits.prior)


def collocation_loss(params, static, mech, data: TrainingData, cfg: TrainConfig, reg=None):
    """The periodic objective with every orbit collocated, plus the penalties that act in
    the periodic stage."""
    model = resolve(UDE(mech, eqx.combine(params["corr"], static)))
    terms = collocation_terms(model, params, data, cfg)
    return objective_of(terms, data, cfg) + penalty_sum(cfg.penalties, "periodic", model, reg)
