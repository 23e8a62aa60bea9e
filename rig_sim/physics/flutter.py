"""Ground truth of the wind-tunnel aerofoil: the 2+1 DoF unsteady flutter model.

Equations of motion (paper, appendix A.1)::

    M q'' + B(V) q' + S(V) q + f_NL(q) = F,     q = (h, alpha, w)

h is heave (m, positive down as in the paper's sketch), alpha pitch (rad), w the
aerodynamic lag state of the Sears/Jones approximation to Theodorsen's function.
f_NL = (0, k_a2 alpha^2 + k_a3 alpha^3, 0). F = (F_heave, M_pitch, 0): the
actuator pushes on heave; process noise is a random pitch moment.

Parameter values are the AeroelasticCBC.jl "case 2" set quoted in DESIGN.md
(after Abdelkefi et al. 2013). With them the equilibrium loses stability in a
subcritical Hopf bifurcation at V = 23.95 m/s, 2.416 Hz.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np


@dataclass(frozen=True)
class FlutterParams:
    b: float = 0.15          # semi-chord, m
    a: float = -0.5          # elastic axis position, in semi-chords from mid-chord
    rho: float = 1.204       # air density, kg/m^3
    m_w: float = 5.3         # wing mass, kg
    m_T: float = 16.9        # total heaving mass, kg
    I_alpha: float = 0.1726  # pitch inertia, kg m^2
    c_alpha: float = 1.0338  # pitch damping, N m s/rad
    c_h: float = 15.4430     # heave damping, N s/m
    k_alpha: float = 60.291  # linear pitch stiffness, N m/rad
    k_alpha2: float = 774.7  # quadratic pitch stiffness, N m/rad^2
    k_alpha3: float = 3490.7  # cubic pitch stiffness, N m/rad^3
    k_h: float = 3317.8      # heave stiffness, N/m
    x_alpha: float = 0.234   # static imbalance, in semi-chords
    c0: float = 1.0          # Sears/Jones coefficients
    c1: float = 0.165
    c2: float = 0.0455
    c3: float = 0.335
    c4: float = 0.3

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def names(cls) -> list[str]:
        return [f.name for f in fields(cls)]


def flutter_matrices(p: FlutterParams, V: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mass, damping and stiffness matrices (3x3) of the unsteady model at airspeed V."""
    pi = np.pi
    b, a, rho = p.b, p.a, p.rho
    C = p.c0 - p.c1 - p.c3
    D = p.c1 * p.c2 + p.c3 * p.c4
    coupling = p.m_w * p.x_alpha * b  # m_w (b - x_f) in the paper's symbols
    M = np.array([
        [p.m_T + rho * b**2 * pi, coupling - rho * b**3 * pi * a, 0.0],
        [coupling - rho * b**3 * pi * a, p.I_alpha + rho * b**4 * pi * (1 / 8 + a**2), 0.0],
        [0.0, 0.0, 1.0],
    ])
    B = np.array([
        [p.c_h + 2 * pi * rho * b * V * C,
         rho * b**2 * pi * V + 2 * pi * rho * b**2 * V * (0.5 - a) * C,
         2 * pi * rho * V**2 * b * D],
        [-2 * pi * rho * b**2 * V * (a + 0.5) * C,
         p.c_alpha + rho * b**3 * pi * V * (0.5 - a)
         - 2 * rho * b**3 * V * pi * (0.5 - a) * (0.5 + a) * C,
         -2 * pi * rho * b**2 * V**2 * (a + 0.5) * D],
        [-1.0 / b, -(0.5 - a), (p.c2 + p.c4) * V / b],
    ])
    S = np.array([
        [p.k_h, 2 * pi * rho * b * V**2 * C, 2 * pi * rho * V**3 * p.c2 * p.c4 * (p.c1 + p.c3)],
        [0.0, p.k_alpha - 2 * pi * rho * b**2 * V**2 * (0.5 + a) * C,
         -2 * pi * rho * b**2 * V**3 * (0.5 + a) * p.c2 * p.c4 * (p.c3 + p.c1)],
        [0.0, -V / b, p.c2 * p.c4 * V**2 / b**2],
    ])
    return M, B, S


def flutter_jacobian(p: FlutterParams, V: float) -> np.ndarray:
    """Jacobian of the first-order system at the equilibrium q = 0 (state (q, q'))."""
    M, B, S = flutter_matrices(p, V)
    Minv = np.linalg.inv(M)
    return np.block([[np.zeros((3, 3)), np.eye(3)], [-Minv @ S, -Minv @ B]])


def flutter_kernel_params(p: FlutterParams, V: float) -> np.ndarray:
    """Flat float64 vector the compiled kernel reads: M^-1 (9), B (9), S (9), k_a2, k_a3, k_a, k_h.

    Recomputed only when the airspeed changes, so the per-sample work is a few
    3x3 products.
    """
    M, B, S = flutter_matrices(p, V)
    return np.concatenate([np.linalg.inv(M).ravel(), B.ravel(), S.ravel(),
                           [p.k_alpha2, p.k_alpha3, p.k_alpha, p.k_h]])


FLUTTER_STATE = ("h", "alpha", "w", "h_dot", "alpha_dot", "w_dot")
FLUTTER_DOF = ("h", "alpha")
