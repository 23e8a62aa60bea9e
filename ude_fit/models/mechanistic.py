"""Models as data: mechanistic right-hand sides, the neural correction, and the UDE.

Every model is an immutable ``equinox.Module`` (a pytree of float64 arrays). A
model never integrates itself; the numerics in ``_flow``, ``_continuation`` and
``_train`` are functions *over* models, so a fitted model can be saved, loaded,
compared and traced by the same code whatever is inside it.

Conventions (both systems)
--------------------------
* State ``y = (q, q')``: aerofoil ``(h, alpha, h', alpha')`` in m, rad, m/s,
  rad/s; oscillator ``(x, x')`` in m, m/s.
* A :class:`Drive` carries what the outside world imposes: the bifurcation
  parameter ``param`` (airspeed in m/s, or base-acceleration amplitude in m/s^2),
  the angular frequency ``omega`` (rad/s; oscillator only) and the Fourier
  coefficients ``fc`` (a0, a1..a7, b1..b7) of the base excitation in m/s^2,
  which for continuation is ``param * cos(omega t)``.
* A correction ``U`` returns generalised forces added on the right-hand side:
  aerofoil ``M q'' = F_mech + U``, oscillator ``x'' = F_mech + U`` (per unit mass).
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._fourier import K, NCOEF


class Drive(eqx.Module):
    """The imposed inputs: bifurcation parameter, forcing frequency and forcing series."""
    param: jax.Array
    omega: jax.Array
    # (15,) Fourier coefficients of the imposed input in the phase omega t: the base
    # acceleration (m/s^2) on the oscillator; on the aerofoil the holding control's force
    # on heave (N) when a fit takes it as a known input, else zeros (the open-loop system)
    fc: jax.Array

    @staticmethod
    def of(param, omega=0.0, fc=None) -> "Drive":
        fc = jnp.zeros(NCOEF) if fc is None else jnp.asarray(fc, dtype=float)
        return Drive(jnp.asarray(param, dtype=float), jnp.asarray(omega, dtype=float), fc)

    @staticmethod
    def harmonic(param, omega) -> "Drive":
        """Pure cosine excitation of amplitude ``param``: what continuation in the amplitude uses."""
        fc = jnp.zeros(NCOEF).at[1].set(1.0) * jnp.asarray(param, dtype=float)
        return Drive(jnp.asarray(param, dtype=float), jnp.asarray(omega, dtype=float), fc)

    def excitation(self, t):
        k = jnp.arange(1, K + 1)
        ph = k * self.omega * t
        return (self.fc[0] + jnp.sum(self.fc[1:K + 1] * jnp.cos(ph))
                + jnp.sum(self.fc[K + 1:] * jnp.sin(ph)))


# ---------------------------------------------------------------------------------------
# mechanistic models
# ---------------------------------------------------------------------------------------

class MechanisticModel(eqx.Module):
    """What every mechanistic model is to the rest of ude_fit; per-system behaviour lives
    in the subclasses' methods, so nothing downstream tests which system it holds.

    A subclass sets ``system`` (the command line's name), ``n_dof``, ``known`` and
    ``fitted`` (field names), ``autonomous`` (no time-dependent forcing: the period is an
    unknown and every orbit has a trivial Floquet multiplier), and defines ``force``,
    ``mass``, ``regressors``, ``parameter_feature`` and ``accelerations``."""

    system: ClassVar[str]
    n_dof: ClassVar[int]
    known: ClassVar[tuple[str, ...]] = ()
    fitted: ClassVar[tuple[str, ...]] = ()
    autonomous: ClassVar[bool]
    # names of fitted values no passive structure has at or below zero
    must_be_positive: ClassVar[tuple[str, ...]] = ()
    # whether a fit holds a stable orbit's period-doubling and torus tests at a margin (see
    # secondary_indicators). A self-excited system's stable orbits sit clear of both; a
    # lightly damped forced one's torus test is its damping per period (about 0.2 on the
    # oscillator rig), which may lie below any fixed margin
    holds_secondary_tests: ClassVar[bool] = False

    @property
    def base(self) -> "MechanisticModel":
        """The model without added effects (itself, unless refined)."""
        return self

    @property
    def effects(self) -> tuple:
        """The added effects (none, unless refined)."""
        return ()

    @property
    def n_hidden(self) -> int:
        """Hidden states after (q, q') (none, unless an added effect has dynamics)."""
        return 0

    def parameter_feature(self, drive: "Drive"):
        """What a correction sees of the drive besides the states."""
        raise NotImplementedError

    def accelerations(self, F, t, drive: "Drive"):
        """q'' from the generalised force F (everything but inertia) at time t."""
        raise NotImplementedError

    def residual_force(self, qdd, F, t, drive: "Drive"):
        """The generalised force the model leaves unexplained when the measured
        accelerations are qdd and its own force is F: what a correction must supply."""
        raise NotImplementedError

    @classmethod
    def incidence_load(cls, param, geometry: dict | None = None):
        """(n_samples, n_dof) the generalised force, at the parameters ``param``, of a unit
        offset between the rig's rest position and its load-free one (an aerofoil's
        zero-lift incidence); None where the model has no such load."""
        return None

    def unphysical(self) -> str:
        """The fitted values no passive structure has, below zero ("name = value, ...";
        "" if none)."""
        # zero is where a sign-constrained identification stops (training.identify): a
        # limit, not a sign error
        return ", ".join(f"{n} = {float(getattr(self, n)):.4g}" for n in self.must_be_positive
                         if float(getattr(self, n)) < 0)

    def parameters(self) -> dict:
        """Every fitted value by name (added effects' coefficients included)."""
        return {f: float(getattr(self, f)) for f in self.fitted}

    def values(self) -> dict:
        """Every value by name, known geometry and fitted (added effects' coefficients
        included)."""
        return parameters_of(self)

    @classmethod
    def from_values(cls, values: dict, geometry: dict | None = None) -> "MechanisticModel":
        """The model with identified ``values`` (names of ``fitted``; others are ignored)
        on the known ``geometry`` (the design values where None)."""
        raise NotImplementedError

    @classmethod
    def equation_error(cls, y, qdd, param, excitation, geometry: dict | None = None):
        """Equation-error rows on flat samples (N, ...): A (N, n_dof, len(fitted)) and the
        known part b (N, n_dof) with ``A theta = b``, and the unfitted model."""
        raise NotImplementedError

    @classmethod
    def sample_states(cls, ys: np.ndarray, param: np.ndarray) -> dict:
        """The named states the effect library's formulas read, from flat samples
        ``ys`` (N, >= 2 n_dof) and their parameter values ``param`` (N,)."""
        raise NotImplementedError

    def stability_indicator(self, M):
        """Positive for a stable periodic orbit with monodromy matrix M, negative once a
        real multiplier passes 1 (smooth in M; no eigen-decomposition)."""
        A = jnp.eye(M.shape[0]) - M
        if not self.autonomous:
            return jnp.linalg.det(A)
        # the trivial multiplier factored out: d/dlambda det(lambda I - M) at 1 = sum of
        # the principal (n-1)-minors of I - M = prod over the others of (1 - mu)
        k = A.shape[0]
        return sum(jnp.linalg.det(jnp.delete(jnp.delete(A, i, 0), i, 1)) for i in range(k))

    def secondary_indicators(self, M, fold=None):
        """The two other ways a stable orbit loses its stability, as smooth test functions
        of its monodromy matrix M, (period doubling, torus): each positive while every
        non-trivial multiplier is inside the unit circle, and changing sign as a real one
        passes -1 (prod of 1 + mu) or a complex pair crosses the circle (prod over pairs of
        1 - mu_i mu_j, from the exterior square of M). :meth:`stability_indicator` sees
        neither: a pair's (1 - mu)(1 - conj mu) and a 1 - mu at mu = -1 stay positive.
        The trivial multiplier's factors are taken out; the torus test is meaningful where
        the fold test is positive (a real multiplier past 1 is a loss already), +inf where
        it is not; ``fold``: :meth:`stability_indicator` of M where the caller has it."""
        n = M.shape[0]
        flip = jnp.linalg.det(jnp.eye(n) + M)
        pairs = jnp.linalg.det(jnp.eye(n * (n - 1) // 2) - _exterior_square(M))
        if not self.autonomous:
            return jnp.stack([flip, pairs])
        # the trivial multiplier gives 1 + 1 in the first; in the second, its products with
        # the others give exactly the fold test's factors
        fold = self.stability_indicator(M) if fold is None else fold
        positive = fold > 0
        torus = jnp.where(positive, pairs / jnp.where(positive, fold, 1.0), jnp.inf)
        return jnp.stack([flip / 2.0, torus])


def _solve_2x2(M, rhs):
    """M^-1 rhs for a 2 x 2 matrix, by Cramer's rule. In an integrator's inner loop a
    general solve is a library call per step, which on a CPU cost the aerofoil's shooting
    loss a quarter of its time; a mass matrix is symmetric positive definite, so the
    closed form is as accurate."""
    det = M[0, 0] * M[1, 1] - M[0, 1] * M[1, 0]
    return jnp.stack([M[1, 1] * rhs[0] - M[0, 1] * rhs[1],
                      M[0, 0] * rhs[1] - M[1, 0] * rhs[0]]) / det


def _exterior_square(M):
    """The exterior square of M: entries M_ik M_jl - M_il M_jk over index pairs i < j,
    k < l; its eigenvalues are the products mu_i mu_j of M's over i < j."""
    i, j = np.triu_indices(M.shape[0], 1)
    return M[i][:, i] * M[j][:, j] - M[i][:, j] * M[j][:, i]


class FlutterQS(MechanisticModel):
    """Quasi-steady 2-DoF aerofoil (the paper's appendix A.2).

    ``M(V) q'' + B(V) q' + S(V) q + (0, k_alpha2 alpha^2 + k_alpha3 alpha^3) = 0``.
    Geometry and inertia (``b, a, rho, m_w, m_T, I_alpha, x_alpha``) are taken as
    known; damping and stiffness are what :func:`identify` estimates from data.
    """
    b: jax.Array
    a: jax.Array
    rho: jax.Array
    m_w: jax.Array
    m_T: jax.Array
    I_alpha: jax.Array
    x_alpha: jax.Array
    c_h: jax.Array
    c_alpha: jax.Array
    k_h: jax.Array
    k_alpha: jax.Array
    k_alpha2: jax.Array
    k_alpha3: jax.Array

    system: ClassVar[str] = "flutter"
    n_dof: ClassVar[int] = 2
    known: ClassVar[tuple[str, ...]] = ("b", "a", "rho", "m_w", "m_T", "I_alpha", "x_alpha")
    fitted: ClassVar[tuple[str, ...]] = ("c_h", "c_alpha", "k_h", "k_alpha", "k_alpha2",
                                         "k_alpha3")
    autonomous: ClassVar[bool] = True
    must_be_positive: ClassVar[tuple[str, ...]] = ("c_h", "c_alpha", "k_h", "k_alpha")
    holds_secondary_tests: ClassVar[bool] = True

    def parameter_feature(self, drive: Drive):
        return drive.param                     # the airspeed

    def _control(self, t, drive: Drive):
        """The imposed force (N) on heave: the holding control, when given as an input."""
        return jnp.array([1.0, 0.0]) * drive.excitation(t)

    def accelerations(self, F, t, drive: Drive):
        return _solve_2x2(self.mass(drive.param), F + self._control(t, drive))

    def residual_force(self, qdd, F, t, drive: Drive):
        return self.mass(drive.param) @ qdd - F - self._control(t, drive)

    def library_states(self, q, qd, drive: Drive) -> dict:
        """The named states the effect library's formulas read."""
        return {"h": q[0], "al": q[1], "hd": qd[0], "ad": qd[1], "V": drive.param,
                "b": self.b, "a": self.a}

    @classmethod
    def nominal(cls, **values) -> "FlutterQS":
        """The design values, with ``values`` in their place."""
        return flutter_qs(**values)

    @classmethod
    def from_values(cls, values: dict, geometry: dict | None = None) -> "FlutterQS":
        known = dict(FLUTTER_NOMINAL if geometry is None else geometry)
        return flutter_qs(**{**known, **{k: v for k, v in values.items() if k in cls.fitted}})

    @classmethod
    def equation_error(cls, y, qdd, param, excitation, geometry: dict | None = None):
        mech = flutter_qs(**dict(FLUTTER_NOMINAL if geometry is None else geometry))
        # the mass and aerodynamic matrices depend on V only: one evaluation per airspeed
        # (the samples stay in their order)
        A = np.empty((len(param), cls.n_dof, len(cls.fitted)))
        b = np.empty((len(param), cls.n_dof))
        nd = cls.n_dof
        for V in np.unique(param):
            m = param == V
            Am, known = mech.regressors(jnp.asarray(y[m, :nd]), jnp.asarray(y[m, nd:2 * nd]),
                                        jnp.asarray(qdd[m]), V)
            A[m] = np.asarray(Am)
            b[m] = -np.asarray(known)
        b[:, 0] += np.asarray(excitation, float)     # the imposed heave force (zero open loop)
        return A, b, mech

    @classmethod
    def sample_states(cls, ys: np.ndarray, param: np.ndarray) -> dict:
        return {"h": ys[:, 0], "al": ys[:, 1], "hd": ys[:, 2], "ad": ys[:, 3], "V": param,
                # the known geometry (semichord, elastic-axis position), as the model has it
                "b": FLUTTER_NOMINAL["b"], "a": FLUTTER_NOMINAL["a"]}

    def mass(self, V):
        pi, b, a, rho = jnp.pi, self.b, self.a, self.rho
        m12 = self.m_w * self.x_alpha * b - rho * pi * b ** 3 * a
        return jnp.array([[self.m_T + rho * pi * b ** 2, m12],
                          [m12, self.I_alpha + rho * pi * b ** 4 * (0.125 + a ** 2)]])

    def aero_damping(self, V):
        pi, b, a, rho = jnp.pi, self.b, self.a, self.rho
        return jnp.array([[2 * pi * rho * b * V, 2 * pi * rho * b ** 2 * V * (1 - a)],
                          [-2 * pi * rho * b ** 2 * V * (a + 0.5),
                           -2 * a * rho * b ** 3 * V * pi * (0.5 - a)]])

    @classmethod
    def incidence_load(cls, param, geometry: dict | None = None):
        """The lift and moment of a unit zero-lift incidence: the aerodynamic stiffness's
        pitch column, as the aerodynamic terms act on alpha less that incidence."""
        mech = cls.from_values({}, geometry)
        return np.asarray(jax.vmap(lambda V: mech.aero_stiffness(V)[:, 1])(
            jnp.asarray(param, float)))

    def aero_stiffness(self, V):
        pi, b, a, rho = jnp.pi, self.b, self.a, self.rho
        return jnp.array([[0.0, 2 * pi * rho * b * V ** 2],
                          [0.0, -2 * pi * rho * b ** 2 * V ** 2 * (0.5 + a)]])

    def force(self, q, qd, drive: Drive):
        """Generalised force of everything but inertia: F = -(B q' + S q + f_NL)."""
        V = drive.param
        h, al = q[0], q[1]
        struct = jnp.array([self.c_h * qd[0] + self.k_h * h,
                            self.c_alpha * qd[1] + self.k_alpha * al
                            + self.k_alpha2 * al ** 2 + self.k_alpha3 * al ** 3])
        return -(struct + self.aero_damping(V) @ qd + self.aero_stiffness(V) @ q)

    def regressors(self, q, qd, qdd, V):
        """Equation-error form: columns multiplying the fitted parameters, and the known part.

        Row i of ``M q'' + B q' + S q + f_NL = 0`` is ``known_i + sum_j A_ij theta_j``.
        """
        h, al = q[..., 0], q[..., 1]
        z = jnp.zeros_like(h)
        A1 = jnp.stack([qd[..., 0], z, h, z, z, z], -1)
        A2 = jnp.stack([z, qd[..., 1], z, al, al ** 2, al ** 3], -1)
        M = self.mass(V)
        known = (jnp.einsum("ij,...j->...i", M, qdd)
                 + jnp.einsum("ij,...j->...i", self.aero_damping(V), qd)
                 + jnp.einsum("ij,...j->...i", self.aero_stiffness(V), q))
        return jnp.stack([A1, A2], -2), known


class Duffing7(MechanisticModel):
    """Base-excited oscillator with 3rd, 5th and 7th-order stiffness (per unit mass).

    ``x'' = -b x' - w2 x - c3 x^3 - c5 x^5 - c7 x^7 + g a_base(t)``; ``g`` is the
    forcing gain (about -1 for a pure base excitation).
    """
    damping: jax.Array
    w2: jax.Array
    c3: jax.Array
    c5: jax.Array
    c7: jax.Array
    g: jax.Array

    system: ClassVar[str] = "oscillator"
    n_dof: ClassVar[int] = 1
    fitted: ClassVar[tuple[str, ...]] = ("damping", "w2", "c3", "c5", "c7", "g")
    autonomous: ClassVar[bool] = False

    def parameter_feature(self, drive: Drive):
        return drive.omega                     # the forcing frequency (the paper's U(x, y; w))

    def accelerations(self, F, t, drive: Drive):
        return F + self.g * drive.excitation(t)

    def residual_force(self, qdd, F, t, drive: Drive):
        return qdd - F - self.g * drive.excitation(t)

    def library_states(self, q, qd, drive: Drive) -> dict:
        return {"x": q[0], "xd": qd[0], "w": drive.omega}

    @classmethod
    def nominal(cls, **values) -> "Duffing7":
        return duffing7(**values)

    @classmethod
    def from_values(cls, values: dict, geometry: dict | None = None) -> "Duffing7":
        return duffing7(**{k: v for k, v in values.items() if k in cls.fitted})

    @classmethod
    def equation_error(cls, y, qdd, param, excitation, geometry: dict | None = None):
        mech = duffing7()
        A, known = mech.regressors(jnp.asarray(y[:, :1]), jnp.asarray(y[:, 1:2]),
                                   jnp.asarray(qdd), jnp.asarray(excitation))
        return np.asarray(A), -np.asarray(known), mech

    @classmethod
    def sample_states(cls, ys: np.ndarray, param: np.ndarray) -> dict:
        return {"x": ys[:, 0], "xd": ys[:, 1]}

    def mass(self, param):
        return jnp.eye(1)

    def force(self, q, qd, drive: Drive, t=0.0):
        x = q[0]
        f = (-self.damping * qd[0] - self.w2 * x - self.c3 * x ** 3 - self.c5 * x ** 5
             - self.c7 * x ** 7)
        return jnp.array([f])

    def regressors(self, q, qd, qdd, exc):
        x = q[..., 0]
        A = jnp.stack([qd[..., 0], x, x ** 3, x ** 5, x ** 7, -exc], -1)[..., None, :]
        return A, qdd


FLUTTER_NOMINAL = dict(b=0.15, a=-0.5, rho=1.204, m_w=5.3, m_T=16.9, I_alpha=0.1726,
                       x_alpha=0.234, c_h=15.4430, c_alpha=1.0338, k_h=3317.8, k_alpha=60.291,
                       k_alpha2=774.7, k_alpha3=3490.7)


def flutter_qs(**values) -> FlutterQS:
    """A quasi-steady aerofoil; unspecified parameters take the DESIGN case-2 values."""
    unknown = set(values) - set(FLUTTER_NOMINAL)
    if unknown:
        raise ValueError(f"unknown aerofoil parameter(s): {', '.join(sorted(unknown))}")
    vals = {**FLUTTER_NOMINAL, **values}
    return FlutterQS(**{k: jnp.asarray(float(v)) for k, v in vals.items()})


def duffing7(**values) -> Duffing7:
    base = dict(damping=1.0, w2=(2 * np.pi * 18) ** 2, c3=0.0, c5=0.0, c7=0.0, g=-1.0)
    unknown = set(values) - set(base)
    if unknown:
        raise ValueError(f"unknown oscillator parameter(s): {', '.join(sorted(unknown))}")
    return Duffing7(**{k: jnp.asarray(float(v)) for k, v in {**base, **values}.items()})


# the command line's --system names, and the mechanistic model of each
SYSTEMS: dict[str, type[MechanisticModel]] = {"flutter": FlutterQS, "oscillator": Duffing7}


def model_class(system: str) -> type[MechanisticModel]:
    if system not in SYSTEMS:
        raise ValueError(f"unknown system {system!r} ({' or '.join(SYSTEMS)})")
    return SYSTEMS[system]


def parameters_of(mech) -> dict:
    return {f.name: float(getattr(mech, f.name)) for f in dataclasses.fields(mech)}

