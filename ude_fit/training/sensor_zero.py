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
    error_own_means: float      # equation error (weighted RMS) with each point's own mean
    error: float                # ... with the zero used
    # the offset between the rest position and the load-free one (an aerofoil's zero-lift
    # incidence, rad), identified with the zero; None where the model has no such load
    incidence: float | None
    # (n_coord,) how far the rest position moves over the points' parameters under its load
    deflection_span: tuple[float, ...]

    def to_json(self) -> dict:
        finite = lambda xs: [x if math.isfinite(x) else None for x in xs]
        return {"coordinates": list(self.coordinates), "offsets": finite(self.offsets),
                "std_error": finite(self.std_error),
                "identified": self.identified, "points": self.points,
                "equation_error_own_means": self.error_own_means,
                "equation_error": self.error, "incidence": self.incidence,
                "deflection_span": list(self.deflection_span),
                "method": ("identified with the mechanistic model's parameters (equation "
                           "error)" if self.identified else
                           "each point's own mean (the points cannot pin a common zero)")}


def _shift(ds: OrbitDataset, unknown: np.ndarray, by: np.ndarray,
           known: bool = True) -> OrbitDataset:
    """``ds`` with the ``unknown`` orbits' means lowered by ``by`` ((n_coord,), or one row
    per orbit) and marked ``known``."""
    by = np.broadcast_to(np.asarray(by, float), (len(ds), len(ds.coordinates)))
    orbits = []
    for o, u, z in zip(ds.orbits, unknown, by):
        if u:
            c = np.array(o.coeffs)
            c[:, 0] -= z
            o = dataclasses.replace(o, coeffs=c, zero_known=known)
        orbits.append(o)
    return dataclasses.replace(ds, orbits=tuple(orbits))


def _angle_turns(ds: OrbitDataset, unknown: np.ndarray) -> np.ndarray:
    """(n_orbits, n_coord) whole turns to take off each orbit's mean so that an angle's lies
    within pi of the first unknown orbit's (an encoder reading near its wrap holds the same
    angle as about 2 pi); zero elsewhere."""
    means = np.array([np.asarray(o.coeffs)[:, 0] for o in ds.orbits])
    first = means[np.flatnonzero(unknown)[0]]
    turns = np.zeros_like(means)
    for j, name in enumerate(ds.coordinates):
        if name in ds.kind.angles:
            turns[:, j] = 2 * np.pi * np.round((means[:, j] - first[j]) / (2 * np.pi))
    return turns


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


def with_sensor_zero(ds: OrbitDataset, base: dict | None = None) -> OrbitDataset:
    """``ds`` with the orbits whose zero no file recorded put about the rig's rest position,
    identified from all points (module docstring), and its :class:`SensorZero` record;
    ``ds`` itself where every orbit's zero is known. ``base``: the mechanistic model's
    known geometry (the design's where None)."""
    unknown = ds.zero_unknown()
    if not unknown.any():
        return ds
    ds = _shift(ds, unknown, _angle_turns(ds, unknown), known=False)
    means = np.array([np.asarray(o.coeffs)[:, 0] for o in ds.orbits])
    start = means[unknown].mean(axis=0)
    # the offsets are searched in units of each coordinate's largest first harmonic
    scale = np.array([max(math.hypot(c[1], c[1 + (c.size - 1) // 2])
                          for c in (np.asarray(o.coeffs)[j] for o in ds.orbits))
                      for j in range(len(ds.coordinates))])
    scale = np.where(scale > 0, scale, 1.0)
    own = _shift(ds, unknown, means)
    data_own = training_data(own, n=SAMPLES)
    w_eq = equation_weights(regression(data_own, ds.system, base)[1])
    error_own = _rms(equation_residual(data_own, ds.system, w_eq, base))

    def residual(x):
        shifted = _shift(ds, unknown, start + x * scale)
        return _residual(training_data(shifted, n=SAMPLES), ds.system, w_eq, base)[0]

    fit = least_squares(residual, np.zeros(len(start)), diff_step=1e-4)
    s = np.linalg.svd(fit.jac, compute_uv=False)
    identified = bool(np.all(np.isfinite(fit.x)) and s[-1] > IDENTIFIABLE * s[0])
    n = len(start)
    if identified:
        zero = start + fit.x * scale
        values = _residual(training_data(_shift(ds, unknown, zero), n=SAMPLES), ds.system,
                           w_eq, base)[1]
        deflection = _static_deflection(ds, values, base)
        out = _shift(ds, unknown, zero + deflection)
        error = _rms(fit.fun)
        dof = max(1, fit.fun.size - fit.x.size - len(values))
        cov = (fit.fun @ fit.fun) / dof * np.linalg.pinv(fit.jac.T @ fit.jac)
        std = np.sqrt(np.clip(np.diag(cov), 0, None)) * scale
        incidence = values.get(INCIDENCE)
        spread = tuple(float(x) for x in np.ptp(deflection[unknown], axis=0))
    else:
        zero = std = np.full(n, np.nan)
        out, error, incidence, spread = own, error_own, None, (0.0,) * n
    record = SensorZero(tuple(ds.coordinates), tuple(float(z) for z in zero),
                        tuple(float(e) for e in std), identified, int(unknown.sum()),
                        error_own, error, incidence, spread)
    return dataclasses.replace(out, sensor_zero=record)


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(r))))
