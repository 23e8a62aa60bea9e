"""The Hopf point's criticality (ude_fit/analysis/criticality.py) against known truth: a
system whose limit cycles are exact circles of known radius (the Hopf normal form, a
stable mode fed by the radius and feeding it back, all mixed by a linear change of
coordinates), sub- and supercritical; and the aerofoil model's branch traced by the
package's own continuation near its Hopf point. (AUTO-07p's side of the sign is in
tests/test_auto07p_reference.py.)"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from ude_fit import UDE, flutter_qs, trace_flutter
from ude_fit.analysis.criticality import hopf_criticality

import jax  # noqa: E402  (after the imports above, before any array)

jax.config.update("jax_enable_x64", True)

MIX = np.array([[1.0, 0.4, 0.3, -0.2],
                [0.2, 0.9, -0.5, 0.1],
                [-0.3, 0.1, 1.2, 0.4],
                [0.5, -0.2, 0.2, 0.8]])


class Circles(eqx.Module):
    """u1, u2: a Hopf normal form with growth rate k (V − V0), frequency omega and cubic
    coefficient a; w' = −lam w + kappa r² feeds back as gamma w on (u1, u2); v' = −v. On
    every periodic orbit w = kappa r² / lam exactly, so the orbits are circles with
    r² = −k (V − V0) / (a + gamma kappa / lam). The state is x = MIX (u1, u2, w, v)."""
    k: float = 0.3
    V0: float = 20.0
    omega: float = 2 * np.pi * 2.4
    a: float | jax.Array = 1.5
    gamma: float | jax.Array = 0.8
    kappa: float = 0.5
    lam: float = 2.0
    n_state: int = eqx.field(static=True, default=4)

    def vector_field(self, t, x, drive):
        T = jnp.asarray(MIX)
        u1, u2, w, v = jnp.linalg.solve(T, x)
        mu = self.k * (drive.param - self.V0)
        r2 = u1 ** 2 + u2 ** 2
        grow = mu + self.a * r2 + self.gamma * w
        du = jnp.stack([grow * u1 - self.omega * u2, self.omega * u1 + grow * u2,
                        -self.lam * w + self.kappa * r2, -v])
        return T @ du

    def amplitude2_slope(self) -> float:
        """dA²/dV of x0's first harmonic: A = r |(MIX00, MIX01)| (w is constant on an orbit)."""
        return float(-self.k * (MIX[0, 0] ** 2 + MIX[0, 1] ** 2)
                     / (self.a + self.gamma * self.kappa / self.lam))


@pytest.mark.parametrize("a, gamma", [(1.5, 0.8), (1.5, -8.0), (-1.0, 0.0)])
def test_the_slope_of_exact_circles(a, gamma):
    # as arrays, so that the three systems share one compilation
    system = Circles(a=jnp.asarray(a), gamma=jnp.asarray(gamma))
    crit = hopf_criticality(system, (15.0, 25.0))
    assert crit.param == pytest.approx(system.V0, abs=1e-9)
    assert crit.amplitude2_slope == pytest.approx(system.amplitude2_slope(), rel=1e-6)
    # subcritical exactly when the orbits lie where the equilibrium is stable (below V0)
    assert crit.subcritical == (system.amplitude2_slope() < 0)
    assert crit.growth_rate_slope == pytest.approx(system.k, rel=1e-6)


def test_the_aerofoil_branch_leaves_its_hopf_point_as_predicted():
    model = UDE(flutter_qs())
    crit = hopf_criticality(model, (5.0, 40.0))
    branch = trace_flutter(model, v_range=(5.0, 40.0), amp_max=0.12,
                           scales=np.array([0.02, 0.1, 0.3, 1.5]))
    A, V = np.asarray(branch.amplitude), np.asarray(branch.param)
    near = A < 0.02 * A.max()           # where the normal form's leading term rules
    assert near.sum() >= 3
    traced = np.polyfit(V[near], A[near] ** 2, 1)[0]
    assert crit.param == pytest.approx(branch.hopf["param"], abs=1e-6)
    assert crit.subcritical and traced < 0
    # (the traced slope carries the next order, O(A²): 1e-4 of it at these amplitudes)
    assert crit.amplitude2_slope == pytest.approx(traced, rel=0.005)
