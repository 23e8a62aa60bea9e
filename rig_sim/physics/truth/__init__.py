"""Ground-truth bifurcation analysis of both rigs.

The campaign tests judge a CBC measurement against *the rig's own truth*: the
periodic orbits of the very right-hand sides the firmware integrates
(``rhs.flutter_deriv`` and ``rhs.oscillator_deriv``, with the same effect
vector), traced here by numerical continuation. Nothing in this module is
fitted or tabulated; every number comes from the equations.

Method (the same for both rigs)
-------------------------------
* **Shooting.** A periodic orbit is a fixed point of the flow over one period.
  The flow is integrated by a compiled fixed-step classical Runge-Kutta scheme
  (``n_steps`` steps per period, default 1000 for the aerofoil and 600 for the
  oscillator; halving the step changes amplitudes by less than 1e-8 relative).
  Because the step count per period is fixed, the discrete flow map is smooth
  in the period and the parameter, so Newton converges quadratically on it.
* **Jacobians by central differences.** All unknowns (initial state, period,
  parameter) are perturbed by +-1e-6 in scaled units and the 2n+1
  trajectories are integrated in one compiled call; the truncation error is
  O(1e-12). The state block plus the identity is the monodromy matrix, whose
  eigenvalues are the Floquet multipliers.
* **Aerofoil (autonomous).** Unknowns (y0, T, V); equations
  ``phi_T(y0) - y0 = 0`` and the phase condition ``h'(0) = 0`` (the orbit
  starts at a heave extremum). One Floquet multiplier is always 1 (a shift
  along the orbit); it is excluded from the stability test.
* **Oscillator (forced).** Period fixed at 1/f; unknowns (y0, Phi) with the
  coil current in y0 (the hidden third state); equations ``phi_T(y0) - y0 = 0``.
* **Pseudo-arclength continuation** in scaled coordinates with a tangent
  predictor, step control by Newton effort and tangent turning angle, and
  fold detection by a sign change of the parameter component of the tangent.
  Each fold is then located to solver precision by a 1-D root find on the
  arclength step (the parameter component of the tangent is zero at a fold).
* **Amplitude metric.** "Amplitude" is always the FIRST-HARMONIC amplitude
  ``sqrt(a1^2 + b1^2)`` of the Fourier series of the coordinate over one
  period (heave h for the aerofoil, tip displacement x for the oscillator),
  computed from the uniformly spaced shooting samples (the trapezoid rule is
  spectrally accurate for periodic data). This is the metric the whole project
  uses.

Stability: an orbit is stable when every non-trivial Floquet multiplier lies
inside the unit circle (modulus < 1).

Modules: `shooting` (compiled integrators, shooting problems), `continuation` (Newton,
pseudo-arclength, folds), `flutter_branch` (the aerofoil), `oscillator_curve` (the oscillator).
"""

from .flutter_branch import (FlutterBranch, flutter_equilibrium_eigenvalues, flutter_hopf,
                             flutter_lco_at, flutter_lco_branch, flutter_orbit_at)
from .oscillator_curve import (ForcedCurve, oscillator_amplitude_at, oscillator_orbit_at,
                               oscillator_scurve)
from .shooting import effect_vector, first_harmonic

__all__ = [
    "FlutterBranch", "ForcedCurve", "effect_vector", "flutter_equilibrium_eigenvalues",
    "flutter_hopf", "flutter_lco_branch", "flutter_lco_at", "flutter_orbit_at",
    "oscillator_scurve", "oscillator_amplitude_at", "oscillator_orbit_at",
    "first_harmonic",
]
