"""Ground truth of the shaker-driven electrodynamic oscillator.

A cantilever with magnets at its tip moves over a coil; the base is driven by a
shaker. Per unit modal mass, with x the tip's displacement relative to the base
(m) and i the coil current (A)::

    x'' = -2 zeta w_n x' - w_n^2 x - c3 x^3 - c5 x^5 - c7 x^7 + (theta/m) i + c_A a_b(t)
    L i' = -R i - theta x'

a_b(t) is the total base acceleration the shaker produces (m/s^2): the host's
forcing Phi cos(w t) plus the embedded controller's output. Sign convention: a
positive base acceleration pushes the tip towards +x.

The coil circuit is the hidden physics: the mechanistic model (7th-order Duffing)
leaves it out. Through it the tip feels a frequency-dependent damping
theta^2 R / (m (R^2 + w^2 L^2)) and a frequency-dependent stiffening
theta^2 w^2 L / (m (R^2 + w^2 L^2)), so one set of Duffing coefficients can only
be right at one forcing frequency.

No published parameter values exist for this device; these were chosen so that
the linear natural frequency is 18 Hz, damping is light (about 2 % of critical
including the coil), the restoring force hardens, and at every forcing frequency
from 20 to 26 Hz the response amplitude against base-acceleration amplitude is an
S-curve (two folds, unstable middle branch) with both folds below the shaker's
100 m/s^2 limit. docs/physics.md shows the resulting diagrams.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np


@dataclass(frozen=True)
class OscillatorParams:
    f_n: float = 18.0        # linear natural frequency, Hz (coil open-circuit)
    zeta: float = 0.006      # mechanical damping ratio
    c3: float = 2.0e8        # cubic stiffness per unit mass, 1/(m^2 s^2)
    c5: float = 5.0e11       # quintic stiffness per unit mass, 1/(m^4 s^2)
    c7: float = 2.0e15       # septic stiffness per unit mass, 1/(m^6 s^2)
    c_A: float = 1.0         # base-acceleration participation factor
    mass: float = 0.1        # modal mass, kg
    theta: float = 3.0       # electromechanical coupling, N/A (= V s/m)
    R: float = 15.0          # coil + load resistance, ohm
    L: float = 0.1           # coil inductance, H
    shaker_limit: float = 100.0  # largest base acceleration the shaker can make, m/s^2

    @property
    def omega_n(self) -> float:
        return 2.0 * np.pi * self.f_n

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def names(cls) -> list[str]:
        return [f.name for f in fields(cls)]

    def coil_damping_and_stiffness(self, omega: float) -> tuple[float, float]:
        """Equivalent per-unit-mass damping (1/s) and stiffness (1/s^2) the coil adds at omega."""
        den = self.R**2 + omega**2 * self.L**2
        k2m = self.theta**2 / self.mass
        return k2m * self.R / den, k2m * omega**2 * self.L / den


def oscillator_kernel_params(p: OscillatorParams) -> np.ndarray:
    """Flat float64 vector the compiled kernel reads."""
    return np.array([
        2.0 * p.zeta * p.omega_n, p.omega_n**2, p.c3, p.c5, p.c7, p.c_A,
        p.theta / p.mass, p.R / p.L, p.theta / p.L,
    ])


OSCILLATOR_STATE = ("x", "x_dot", "i")
OSCILLATOR_DOF = ("x",)
