"""The rig's rest position in the sensors' frame, where the files do not record it.

A wind-tunnel file's heave and pitch are about a sensor zero nobody wrote down (the heave
sensor's DC level, the pitch encoder's absolute angle). Taking each file's own mean as its
zero throws away what an asymmetric restoring force does to an orbit: a quadratic pitch
stiffness pulls a large orbit's mean away from rest in proportion to its amplitude squared,
and its static aerodynamic load moves the heave's mean with it. With every mean set to zero
the equation-error identification mistakes the stiffness (on simulated lee2020-format files
of the design rig: k_alpha 28.6 and k_alpha2 41 instead of 60.3 and 775, a diagram missing
7 of 11 points).

The zero is one for all points of a rig (one sensor, one encoder), so it is identified once,
from all of them: the offsets that leave the mechanistic model's equation error smallest,
its parameters solved for at every trial offset (the same bounded least squares
:func:`~.identify.identify` runs). What pins it is what the model's nonlinear terms do to
an orbit's mean and harmonics (an offset turns a cubic term's odd harmonics into even
ones) and the airspeed-dependent static aerodynamic load; where the points cannot pin it
(the equation error flat along an offset) each point's own mean stays its zero, and the
record says so.

The identification is only as good as the model it runs through: on lee2020/model2, whose
points the mechanistic model misses with either zero, the identified zero lowers the
equation error by 2 % and the default fit's adequate starts from 15, 13, 15 to 13, 10-11, 12
on seeds 0-2; on simulated wind-tunnel files of three held-out configurations, whose points
it meets with the identified zero, it lifts them from 2, 4 and 7 to 16, 16 and 15 of 16
(docs/experiments.md, 2026-12-06/07). So by default (``auto``,
:func:`ude_fit.mechanistic_stage.with_chosen_zero`) the fit takes the identified zero
only where the mechanistic model identified with it reproduces the measured diagram better
than with each point's own mean.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import least_squares

from ..data.orbit import OrbitDataset
from ..models.mechanistic import Drive, model_class
from .identify import (_bounded_solve, _lower_bounds, _weighted, build, equation_residual,
                       equation_weights, regression, training_data)

SAMPLES = 32              # phases per orbit in the regression (the fit's default)
# how steep the equation error must be along every offset, relative to its steepest one (the
# singular values of its Jacobian): flatter is a zero the model's terms do not see
IDENTIFIABLE = 1e-6
INCIDENCE = "incidence"   # the load-free offset's name among the regression's unknowns


@dataclasses.dataclass(frozen=True)
class ZeroJudgement:
    """The mechanistic model identified about one candidate zero, judged by its diagram
    against the measured points: how many it misses and its branch error (None where it
    meets none). The ``auto`` choice takes the candidate that ranks lower."""
    missed: int
    branch_rms: float | None

    def __post_init__(self):
        if isinstance(self.missed, bool) or not isinstance(self.missed, (int, np.integer)) \
                or self.missed < 0:
            raise ValueError(f"missed must be a count of points, not {self.missed!r}")
        b = self.branch_rms
        if b is not None and not (math.isfinite(b) and b >= 0):
            raise ValueError(f"branch_rms must be None or a non-negative number, not {b!r}")

    def rank(self) -> tuple:
        """Fewer points missed first, then the smaller branch error."""
        return (self.missed, math.inf if self.branch_rms is None else self.branch_rms)

    def describe(self, points: int) -> str:
        return f"{self.missed} of {points} points missed" + (
            "" if self.branch_rms is None else f", branch RMS {100 * self.branch_rms:.3g} %")

    def to_json(self) -> dict:
        return {"missed": int(self.missed), "branch_rms": self.branch_rms}


@dataclasses.dataclass(frozen=True)
class SensorZero:
    """The zero the orbits were put about, per coordinate, in the sensors' frame (the
    loaded means), and how well the mechanistic model's equations hold with it."""
    coordinates: tuple[str, ...]
    offsets: tuple[float, ...]
    # the offsets' standard errors (least squares, the samples taken as independent: an
    # orbit's samples are not, so this is a lower bound)
    std_error: tuple[float, ...]
    identified: bool            # False: each point's own mean was kept as its zero
    points: int                 # how many points' zeros were unknown
    # equation error (weighted RMS) with each point's own mean, and with the zero used
    # (None where no zero was identified)
    error_own_means: float | None
    error: float | None
    # the offset between the rest position and the load-free one (an aerofoil's zero-lift
    # incidence, rad), identified with the zero; None where the model has no such load
    incidence: float | None
    # (n_coord,) how far the rest position moves over the points' parameters under its load
    deflection_span: tuple[float, ...]
    method: str
    # where the zero was chosen between each point's own mean and the identified one
    # (``auto``): the mechanistic model's diagram with each, by the choice's name; None
    # otherwise
    judged: dict[str, ZeroJudgement] | None = None

    def to_json(self) -> dict:
        finite = lambda xs: [x if math.isfinite(x) else None for x in xs]
        return {"coordinates": list(self.coordinates), "offsets": finite(self.offsets),
                "std_error": finite(self.std_error),
                "identified": self.identified, "points": self.points,
                "equation_error_own_means": self.error_own_means,
                "equation_error": self.error, "incidence": self.incidence,
                "deflection_span": list(self.deflection_span), "method": self.method,
                "judged": (None if self.judged is None
                           else {k: j.to_json() for k, j in self.judged.items()})}


def _about(ds: OrbitDataset, unknown: np.ndarray, means: np.ndarray,
           zero: np.ndarray) -> OrbitDataset:
    """``ds`` with the ``unknown`` orbits' means set to their sensor-frame ``means`` (one row
    per orbit) less ``zero`` ((n_coord,) or one row per orbit), their zero now known."""
    zero = np.broadcast_to(np.asarray(zero, float), means.shape)
    orbits = []
    for o, u, m, z in zip(ds.orbits, unknown, means, zero):
        if u:
            c = np.array(o.coeffs)
            c[:, 0] = m - z
            o = dataclasses.replace(o, coeffs=c, sensor_means=None)
        orbits.append(o)
    return dataclasses.replace(ds, orbits=tuple(orbits))


def _sensor_means(ds: OrbitDataset, unknown: np.ndarray) -> np.ndarray:
    """(n_orbits, n_coord) the unknown orbits' sensor-frame means (zeros elsewhere), an
    angle's brought within pi of the first unknown orbit's (an encoder reading near its wrap
    holds the same angle as about 2 pi)."""
    means = np.array([np.zeros(len(ds.coordinates)) if o.sensor_means is None
                      else np.asarray(o.sensor_means) for o in ds.orbits])
    first = means[np.flatnonzero(unknown)[0]]
    for j, name in enumerate(ds.coordinates):
        if name in ds.kind.angles:
            means[:, j] -= 2 * np.pi * np.round((means[:, j] - first[j]) / (2 * np.pi))
    return means


def _incidence_columns(data, system: str, base: dict | None):
    """The regression's column of an unknown load-free offset (None where the model has
    no such load): its force enters with a minus sign, as an effect's does."""
    load = model_class(system).incidence_load(np.repeat(np.asarray(data.drive.param),
                                                        data.ys.shape[1]), base)
    return None if load is None else -load[:, :, None]


def _residual(data, system: str, w_eq, base):
    """The weighted equation error left by the bounded solve with the load-free offset
    among the unknowns, and the solution by name."""
    A, b, names, _ = regression(data, system, base)
    extra = _incidence_columns(data, system, base)
    lower = _lower_bounds(system, names)
    if extra is not None:
        A = np.concatenate([A, extra], axis=2)
        names, lower = names + [INCIDENCE], np.append(lower, -np.inf)
    Aw, bw, col = _weighted(A, b, w_eq)
    theta = _bounded_solve(Aw / col, bw, lower) / col
    return bw - Aw @ theta, dict(zip(names, theta.tolist()))


def _static_deflection(ds: OrbitDataset, values: dict, base: dict | None) -> np.ndarray:
    """(n_orbits, n_coord) each orbit's rest position under the load-free offset's load at
    its parameter: the identified model's linear stiffness there, solved against it."""
    incidence = values.get(INCIDENCE, 0.0)
    if not incidence:
        return np.zeros((len(ds), len(ds.coordinates)))
    mech = build(ds.system, base, values)
    zero = jnp.zeros(mech.n_dof)
    load = model_class(ds.system).incidence_load(ds.parameters(), base) * incidence
    out = []
    for V, f in zip(ds.parameters(), load):
        stiffness = -jax.jacfwd(lambda q: mech.force(q, zero, Drive.of(V)))(zero)
        out.append(np.linalg.solve(np.asarray(stiffness), f))
    return np.asarray(out)


SENSOR_ZERO = ("own-means", "identified")      # what a fit takes as the sensors' zero
# what a user may ask for: one of them, or the one whose mechanistic model meets the
# measured diagram better (ude_fit.mechanistic_stage.with_chosen_zero)
AUTO = "auto"
SENSOR_ZERO_CHOICES = (AUTO, *SENSOR_ZERO)


def with_sensor_zero(ds: OrbitDataset, base: dict | None = None,
                     zero: str = "own-means") -> OrbitDataset:
    """``ds`` with its :class:`SensorZero` record where some file did not record the rig's
    rest position (``ds`` itself where every orbit's is known). ``zero``: "own-means"
    leaves each such orbit about its own mean (as loaded); "identified" puts them about
    the rest position identified from all points (module docstring) and each about its
    own parameter's rest position under the load-free offset's load. ``base``: the
    mechanistic model's known geometry (the design's where None). A dataset whose zero was
    already chosen (it carries the record) comes back as it is."""
    if zero not in SENSOR_ZERO:
        raise ValueError(f"the sensors' zero must be {' or '.join(SENSOR_ZERO)}, not "
                         f"{zero!r}")
    unknown = ds.zero_unknown()
    if not unknown.any() or ds.sensor_zero is not None:
        return ds
    n = len(ds.coordinates)
    nothing = tuple(np.full(n, np.nan))
    if zero == "own-means":
        return dataclasses.replace(ds, sensor_zero=SensorZero(
            tuple(ds.coordinates), nothing, nothing, False, int(unknown.sum()), None, None,
            None, (0.0,) * n, "each point's own mean"))
    data_own = training_data(ds, n=SAMPLES)
    w_eq = equation_weights(regression(data_own, ds.system, base)[1])
    error_own = _rms(equation_residual(data_own, ds.system, w_eq, base))
    means = _sensor_means(ds, unknown)
    start = means[unknown].mean(axis=0)
    # the offsets are searched in units of each coordinate's largest first harmonic
    scale = np.array([max(math.hypot(c[1], c[1 + (c.size - 1) // 2])
                          for c in (np.asarray(o.coeffs)[j] for o in ds.orbits))
                      for j in range(n)])
    scale = np.where(scale > 0, scale, 1.0)

    def residual(x):
        shifted = _about(ds, unknown, means, start + x * scale)
        return _residual(training_data(shifted, n=SAMPLES), ds.system, w_eq, base)[0]

    fit = least_squares(residual, np.zeros(n), diff_step=1e-4)
    s = np.linalg.svd(fit.jac, compute_uv=False)
    if not (np.all(np.isfinite(fit.x)) and s[-1] > IDENTIFIABLE * s[0]):
        return dataclasses.replace(ds, sensor_zero=SensorZero(
            tuple(ds.coordinates), nothing, nothing, False, int(unknown.sum()), error_own,
            error_own, None, (0.0,) * n,
            "each point's own mean (the points cannot pin a common zero)"))
    offsets = start + fit.x * scale
    values = _residual(training_data(_about(ds, unknown, means, offsets), n=SAMPLES),
                       ds.system, w_eq, base)[1]
    deflection = _static_deflection(ds, values, base)
    dof = max(1, fit.fun.size - fit.x.size - len(values))
    cov = (fit.fun @ fit.fun) / dof * np.linalg.pinv(fit.jac.T @ fit.jac)
    std = np.sqrt(np.clip(np.diag(cov), 0, None)) * scale
    record = SensorZero(tuple(ds.coordinates), tuple(float(z) for z in offsets),
                        tuple(float(e) for e in std), True, int(unknown.sum()), error_own,
                        _rms(fit.fun), values.get(INCIDENCE),
                        tuple(float(x) for x in np.ptp(deflection[unknown], axis=0)),
                        "identified with the mechanistic model's parameters (equation "
                        "error)")
    out = _about(ds, unknown, means, offsets + deflection)
    return dataclasses.replace(out, sensor_zero=record)


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(r))))
