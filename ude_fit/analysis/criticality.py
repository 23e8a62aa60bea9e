"""Which way a Hopf point's branch leaves it: the first Lyapunov coefficient of the
equilibrium at the Hopf point, and the slope of the branch's squared amplitude in the
parameter that it implies, to set beside the data's own (the unstable orbits' amplitude²
line, :func:`ude_fit.data.estimates.unstable_amplitude_line`).

Near a Hopf point the dynamics on the centre manifold reduce to the Poincaré normal form
z' = (mu(V) + i omega) z + c1 z |z|², so the periodic orbits have |z|² = −mu / Re c1: the
bifurcation is subcritical (unstable orbits where the equilibrium is stable) for Re c1 > 0
and supercritical for Re c1 < 0. With x ≈ q z + conj(q z) the first coordinate's first
harmonic has amplitude A = 2 |q_0| |z|, so along the branch

    dA²/dV = −4 |q_0|² mu'(V_H) / Re c1.

c1 follows Kuznetsov's formula (Elements of Applied Bifurcation Theory, 3rd ed., eq. 3.20
and its n-dimensional form, section 5.4): with A q = i omega q, Aᵀ p = −i omega p and
<p, q> = conj(p)·q = 1, and B, C the second and third derivatives of the vector field at the
equilibrium,

    Re c1 = ½ Re[<p, C(q,q,q̄)> − 2 <p, B(q, A⁻¹ B(q,q̄))>
                 + <p, B(q̄, (2 i omega − A)⁻¹ B(q,q))>].

The derivatives are forward-mode directional derivatives of the model's own vector field,
complex arguments by multilinearity, so nothing here depends on the model's form.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..models.equilibria import _equilibrium_scan, hopf_point
from ..models.mechanistic import Drive
from ..models.ude import UDE


@dataclass(frozen=True)
class HopfCriticality:
    """A Hopf point's criticality: ``param`` (V_H), ``re_c1`` (the normal form's cubic
    coefficient's real part, 1/s per unit |z|²), ``growth_rate_slope`` (mu'(V_H), the
    critical eigenvalues' real part per unit of the parameter) and ``amplitude2_slope``
    (dA²/dV of the first coordinate's first harmonic along the branch, m² per unit of
    the parameter)."""
    param: float
    re_c1: float
    growth_rate_slope: float
    amplitude2_slope: float

    @property
    def subcritical(self) -> bool:
        return self.re_c1 > 0

    def to_json(self) -> dict:
        return {"param": self.param, "re_c1": self.re_c1,
                "growth_rate_slope": self.growth_rate_slope,
                "amplitude2_slope": self.amplitude2_slope, "subcritical": self.subcritical}


@eqx.filter_jit
def _multilinear_real(model: UDE, y_eq, V, dirs):
    """The derivative of the vector field at the equilibrium ``y_eq`` along each real
    direction of ``dirs`` in turn: B(u, v) for two, C(u, v, w) for three."""
    d = Drive.of(V)
    g = lambda y: model.vector_field(0.0, y_eq + y, d)
    for u in dirs:
        g = (lambda h, u: (lambda y: jax.jvp(h, (y,), (u,))[1]))(g, u)
    return g(jnp.zeros_like(y_eq))


def _multilinear(model: UDE, y_eq, V, *args) -> np.ndarray:
    """B or C on complex vectors, by multilinearity from real directions."""
    out = 0
    for pick in itertools.product((0, 1), repeat=len(args)):
        dirs = tuple(jnp.asarray(a.imag if s else a.real) for a, s in zip(args, pick))
        out = out + 1j ** sum(pick) * np.asarray(_multilinear_real(model, y_eq, V, dirs))
    return out


def first_lyapunov(model: UDE, V_H: float, y_eq, omega: float) -> tuple[float, np.ndarray]:
    """(Re c1, q) at the Hopf point ``V_H`` with equilibrium ``y_eq`` and frequency
    ``omega`` (rad/s); q has unit norm and p is scaled so that <p, q> = 1."""
    V = jnp.asarray(float(V_H))
    y_eq = jnp.asarray(y_eq)
    A = np.asarray(jax.jacfwd(lambda y: model.vector_field(0.0, y, Drive.of(V)))(y_eq))
    lam, vecs = np.linalg.eig(A)
    q = vecs[:, int(np.argmin(np.abs(lam - 1j * omega)))]
    q = q / np.linalg.norm(q)
    lamT, vecsT = np.linalg.eig(A.T)
    p = vecsT[:, int(np.argmin(np.abs(lamT + 1j * omega)))]
    p = p / np.conj(np.vdot(p, q))                 # <p, q> = conj(p)·q = 1
    B = lambda x, z: _multilinear(model, y_eq, V, x, z)
    qb = np.conj(q)
    n = A.shape[0]
    t1 = np.vdot(p, _multilinear(model, y_eq, V, q, q, qb))
    t2 = np.vdot(p, B(q, np.linalg.solve(A, B(q, qb))))
    t3 = np.vdot(p, B(qb, np.linalg.solve(2j * omega * np.eye(n) - A, B(q, q))))
    return float(0.5 * np.real(t1 - 2 * t2 + t3)), q


def equilibrium_eigenvalues(model, V: float) -> np.ndarray:
    """The linearisation's eigenvalues at rest at the parameter value ``V``."""
    _, lam, _ = _equilibrium_scan(model, jnp.asarray([float(V)]), jnp.zeros(model.n_state))
    return np.asarray(lam).ravel()


def growth_rate_slope(model, V: float, dv: float) -> float:
    """mu'(V): the central difference over ±``dv`` of the largest real part of the
    linearisation's eigenvalues at rest."""
    growth = lambda v: float(np.max(np.real(equilibrium_eigenvalues(model, v))))
    return (growth(V + dv) - growth(V - dv)) / (2 * dv)


def hopf_criticality(model: UDE, v_range, dv: float = 1e-4) -> HopfCriticality | None:
    """The criticality of ``model``'s first Hopf point in ``v_range`` (None without one, or
    where the point is degenerate).
    mu' is a central difference of the equilibrium's largest growth rate over ±``dv``."""
    h = hopf_point(model, v_range)
    if h is None or h["omega"] <= 1e-9 * max(1.0, abs(h["param"])):
        return None         # none, or a real eigenvalue crossing (static divergence)
    try:
        re_c1, q = first_lyapunov(model, h["param"], h["y"], h["omega"])
    except np.linalg.LinAlgError:
        return None         # a zero eigenvalue as well: a degenerate point, no normal form

    mu_dash = growth_rate_slope(model, h["param"], dv)
    slope = -4.0 * abs(q[0]) ** 2 * mu_dash / re_c1 if re_c1 != 0 else float("nan")
    return HopfCriticality(h["param"], re_c1, float(mu_dash), float(slope))
