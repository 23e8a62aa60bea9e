"""A model's orbits under the recorded holding control, at the measured points: the
yardstick for a model of points held with some control.

A point held with some control is an orbit of the *controlled* system, off the open-loop
diagram by as much as the control moved it (2-14 % of the amplitude on a campaign held 5 %
off target). Compared with the open-loop diagram, a model right about the open-loop
system is as far from such a point as the control made it, and a model that is better
about the physics need not look better. Compared with the model's own orbit under the
recorded control (the same known input the identification and the training see), a model
right about the system meets every point.

Each point's controlled orbit is solved from the measured orbit, its unknowns the initial
state and the period (the control is periodic in the orbit's own period, as in the
training): Levenberg-Marquardt steps on the periodic stage's residual
(:func:`~ude_fit.training.losses.orbit_terms`: the samples' misfit and the closure, over
the state scales), then Gauss-Newton steps on the misfit constrained to close. The
closed orbits of the model under the control form a one-parameter family (the period
moves along it); the one nearest the measured orbit is taken. It is the model's if it
closes; its heave
first-harmonic amplitude is then compared with the measured one as the branch error is
(:mod:`.metrics`). A point whose orbit does not close is *missed*.

What a model of such points is judged by (:func:`judged`, the fit's adequacy and the
discovery loop's rule alike) takes from each yardstick what it can say: the amplitude error
from the orbit under the control, and whether the model has an orbit of the measured
stability there from its open-loop diagram. A point's stability label is the open-loop
system's (the lab labels a point by the orbit the control holds without changing it), and
an orbit under a known forcing has no stability to compare: a damped linear model has a
forced orbit under any control, so without the diagram's half a model with no limit cycle
at all would meet every point.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..data.orbit import OrbitDataset
from ..models.flow import rk4_orbit
from .metrics_type import BranchErrors, ModelMetrics, PointError
from ..training.identify import TrainingData, augment
from ..training.options import TrainConfig

ITERATIONS = 30             # Levenberg-Marquardt steps towards the orbit
CLOSING_STEPS = 10          # constrained Gauss-Newton steps (quadratic once near)
# an orbit closes when its end state is within this fraction of the state scales of its
# start: a numerical tolerance, far above the solver's floor and far below any misfit
CLOSED = 1e-6


BRANCHES = ("stable", "unstable")


@dataclass(frozen=True)
class HeldSides:
    """Where the points held invasively lie against a model's open-loop orbits at their
    airspeeds, per branch ("stable", "unstable"): how many above, how many below (a point
    the diagram misses, or of unknown stability, is not counted).

    A held orbit fixes the open-loop orbit only together with how far the control moved
    it. Where a branch's points were all held on one side, nothing in the data tells the
    two apart and the model's form splits them: on the invasive benchmark's campaign (every
    unstable point held above its orbit) the fit left about a third of each displacement
    in its open-loop orbit, and the same points held on both sides removed it
    (docs/experiments.md, sixty-fourth session)."""
    above: dict[str, int]
    below: dict[str, int]

    def __post_init__(self):
        for side in (self.above, self.below):
            if set(side) != set(BRANCHES) or any(
                    isinstance(n, bool) or not isinstance(n, int) or n < 0
                    for n in side.values()):
                raise ValueError(f"held sides must count {BRANCHES} points, not {side!r}")

    @property
    def one_sided(self) -> tuple[str, ...]:
        """The branches with at least two points counted, all on one side."""
        return tuple(b for b in BRANCHES if self.above[b] + self.below[b] >= 2
                     and min(self.above[b], self.below[b]) == 0)

    def warning(self) -> str | None:
        """What to tell the user where a branch was held on one side only (the report and
        ``ude-fit fit`` say it); None where none was."""
        if not self.one_sided:
            return None
        return ("Every invasive point of the " + " and the ".join(self.one_sided)
                + " branch lies on one side of its open-loop orbit. One held orbit per "
                "airspeed fixes the open-loop orbit only together with how far the control "
                "moved it, so there the model's form, not the data, decides the split: "
                "hold each airspeed at two targets, one either side of the orbit "
                "(docs/fitting.md, the control as a known input).")

    def to_json(self) -> dict:
        return {"above": dict(self.above), "below": dict(self.below),
                "one_sided": list(self.one_sided)}


@dataclass(frozen=True)
class ControlledOrbits:
    """Every point's orbit under its recorded control against the measured one: per point
    the orbit's heave amplitude and its error over the largest measured amplitude (missed
    where it does not close), and their summary; ``invasive`` per point, whether its
    holding control was (:mod:`~ude_fit.data.holding`)."""
    errors: BranchErrors
    invasive: tuple[bool, ...] = ()

    def __post_init__(self):
        object.__setattr__(self, "invasive", tuple(bool(x) for x in self.invasive))
        if self.invasive and len(self.invasive) != len(self.points):
            raise ValueError(f"{len(self.invasive)} invasive flags for "
                             f"{len(self.points)} points")

    def held_sides(self, open_loop: ModelMetrics) -> HeldSides:
        """Where the invasive points lie against the same model's open-loop diagram
        (``open_loop``: its metrics at these points)."""
        above, below = dict.fromkeys(BRANCHES, 0), dict.fromkeys(BRANCHES, 0)
        for p, invasive in zip(open_loop.errors.points, self.invasive, strict=True):
            if invasive and not p.missed and p.stable is not None:
                side = above if p.measured > p.model else below
                side["stable" if p.stable else "unstable"] += 1
        return HeldSides(above, below)

    @property
    def points(self) -> tuple[PointError, ...]:
        return self.errors.points

    @property
    def missed(self) -> int:
        return self.errors.summary.missed

    @property
    def branch_rms(self) -> float | None:
        return self.errors.summary.branch_rms

    @property
    def branch_max(self) -> float | None:
        return self.errors.summary.branch_max

    def to_json(self) -> dict:
        return {"branch_rms": self.branch_rms, "branch_max": self.branch_max,
                "missed": self.missed, "errors": [p.error for p in self.points],
                "amplitudes": [p.model for p in self.points]}


def yardstick(control_is_input: bool) -> str:
    """What :func:`judged` compares with the points, in words (records and reports)."""
    return "the orbits under the recorded control" if control_is_input else "the diagram"


def judged(metrics: ModelMetrics, controlled: ControlledOrbits | None) -> ModelMetrics:
    """The figures a model is judged by: its diagram's (``metrics``), or with the control
    as an input (``controlled``: its orbits under the recorded control at the same points)
    each point met where the diagram has an orbit of the measured stability there *and*
    the orbit under the control closes, its error that orbit's (the module's docstring).
    The Hopf point and the folds stay the diagram's."""
    if controlled is None:
        return metrics
    if len(controlled.points) != len(metrics.points):
        raise ValueError(f"{len(controlled.points)} orbits under the control for "
                         f"{len(metrics.points)} points")
    points = []
    for p, c in zip(metrics.points, controlled.points):
        if p.missed or c.missed:
            points.append(PointError(p.parameter, p.frequency, p.measured, p.stable))
        else:
            points.append(PointError(p.parameter, p.frequency, p.measured, p.stable,
                                     model=c.model, error=c.error,
                                     model_stable=p.model_stable))
    a_max = max(p.measured for p in metrics.points)
    return dataclasses.replace(metrics, errors=BranchErrors.of(points, a_max))


def _residual(model, z, ys, period, drive, scale, sw, sub: int, closure_weight: float):
    n, m = ys.shape
    y0 = ys[0] + z[:m] * scale
    T = period * (1.0 + z[m])
    drive = eqx.tree_at(lambda d: d.omega, drive, 2.0 * jnp.pi / T)
    yT, sim = rk4_orbit(model, y0, T, drive, n * sub)
    w = jnp.sqrt(sw / jnp.mean(sw))
    fit = ((sim[::sub] - ys) / scale * w).ravel() / math.sqrt(n * m)
    close = math.sqrt(closure_weight) * (yT - y0) / scale
    return jnp.concatenate([fit, close]), sim[::sub], (yT - y0) / scale


@eqx.filter_jit
def _solve(model, ys, period, drive, scale, sw, sub: int, closure_weight: float):
    """One orbit's controlled orbit: Levenberg-Marquardt steps on the periodic stage's
    residual (misfit and closure, as the training weighs them) bring it near, then
    Gauss-Newton steps on the misfit constrained to close (each solves the constrained
    least-squares step's KKT system) make it an orbit of the model. Returns (samples,
    closure) at the end."""
    parts = lambda z: _residual(model, z, ys, period, drive, scale, sw, sub, closure_weight)
    r = lambda z: parts(z)[0]
    m = ys.shape[1]

    def near(carry, _):
        z, cost, lam = carry
        res, J = r(z), jax.jacfwd(r)(z)
        A = J.T @ J
        dz = -jnp.linalg.solve(A + lam * jnp.diag(jnp.diag(A) + 1e-30), J.T @ res)
        trial = jnp.sum(r(z + dz) ** 2)
        better = jnp.isfinite(trial) & (trial < cost)
        return (jnp.where(better, z + dz, z), jnp.where(better, trial, cost),
                jnp.where(better, lam / 3.0, lam * 4.0)), None

    def closed(z, _):
        fit = lambda z: parts(z)[0][:-m]
        close = lambda z: parts(z)[2]
        rf, Jf, c, Jc = fit(z), jax.jacfwd(fit)(z), close(z), jax.jacfwd(close)(z)
        kkt = jnp.block([[Jf.T @ Jf, Jc.T], [Jc, jnp.zeros((m, m))]])
        rhs = jnp.concatenate([-Jf.T @ rf, -c])
        return z + jnp.linalg.solve(kkt, rhs)[:m + 1], None

    z0 = jnp.zeros(m + 1)
    (z, _, _), _ = jax.lax.scan(near, (z0, jnp.sum(r(z0) ** 2), 1e-3), None,
                                length=ITERATIONS)
    z, _ = jax.lax.scan(closed, z, None, length=CLOSING_STEPS)
    _, sim, closure = parts(z)
    return sim, closure


def controlled_orbits(model, data: TrainingData, ds: OrbitDataset) -> ControlledOrbits:
    """``model``'s orbit under each point's recorded control (``data`` carries it as the
    drive's imposed force, :func:`~ude_fit.training.control.with_control`) against the
    measured orbit (see the module's docstring)."""
    data = augment(data, model.mech)            # an added effect's hidden states
    cfg = TrainConfig().for_system(model.system)
    scale = jnp.asarray(data.y_scale)
    sw = (jnp.ones(data.ys.shape[::2]) if data.state_weight is None
          else jnp.asarray(data.state_weight))
    solve = jax.vmap(lambda ys, T, drive, w: _solve(model, ys, T, drive, scale, w,
                                                    cfg.substeps, cfg.closure_weight))
    sims, closures = solve(data.ys, data.period, data.drive, sw)
    sims, closures = np.asarray(sims), np.asarray(closures)
    a_max = float(ds.amplitudes().max())
    n = sims.shape[1]
    phase = np.exp(-2j * np.pi * np.arange(n) / n)
    points = []
    for o, sim, c in zip(ds.orbits, sims, closures, strict=True):
        measured = dict(parameter=o.parameter, frequency=o.frequency, measured=o.amplitude,
                        stable=o.stable)
        if not (np.all(np.isfinite(sim)) and np.sqrt(np.sum(c ** 2)) <= CLOSED):
            points.append(PointError(**measured))
            continue
        amplitude = 2.0 * abs(np.sum(sim[:, 0] * phase)) / n
        points.append(PointError(**measured, model=float(amplitude),
                                 error=float(abs(amplitude - o.amplitude) / a_max)))
    return ControlledOrbits(BranchErrors.of(points, a_max),
                            tuple(o.holding is not None and o.holding.invasive
                                  for o in ds.orbits))
