"""Write the rigs' true bifurcation diagrams and docs/physics.md.

    python docs/make_physics_figures.py

Everything in docs/physics.md that is a number (parameters, Hopf point, folds,
amplitudes) is computed here from rig_sim.physics (the dataclass defaults and the
truth continuation), so the page cannot drift from the code: edit this script,
not the generated page.
"""

from __future__ import annotations

import sys
from dataclasses import fields
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rig_sim.physics.flutter import FlutterParams  # noqa: E402
from rig_sim.physics.oscillator import OscillatorParams  # noqa: E402
from rig_sim.physics.truth import (  # noqa: E402
    flutter_hopf,
    flutter_lco_at,
    flutter_lco_branch,
    oscillator_scurve,
)

IMG = ROOT / "docs" / "img"
PAGE = ROOT / "docs" / "physics.md"

FLUTTER_UNITS = {
    "b": ("m", "semi-chord"),
    "a": ("-", "elastic-axis position from mid-chord, in semi-chords, positive aft"),
    "rho": ("kg/m^3", "air density"),
    "m_w": ("kg", "wing mass"),
    "m_T": ("kg", "total heaving mass (paper: m)"),
    "I_alpha": ("kg m^2", "pitch inertia (paper: I_A)"),
    "c_alpha": ("N m s/rad", "pitch damping (paper: d_t)"),
    "c_h": ("N s/m", "heave damping (paper: d)"),
    "k_alpha": ("N m/rad", "linear pitch stiffness (paper: s_t)"),
    "k_alpha2": ("N m/rad^2", "quadratic pitch stiffness (paper: s_t2)"),
    "k_alpha3": ("N m/rad^3", "cubic pitch stiffness (paper: s_t3)"),
    "k_h": ("N/m", "heave stiffness (paper: s)"),
    "x_alpha": ("-", "static imbalance in semi-chords: m_w (b - x_f) = m_w x_alpha b"),
    "c0": ("-", "Sears/Jones coefficient"),
    "c1": ("-", "Sears/Jones coefficient"),
    "c2": ("-", "Sears/Jones coefficient"),
    "c3": ("-", "Sears/Jones coefficient"),
    "c4": ("-", "Sears/Jones coefficient"),
}

OSCILLATOR_UNITS = {
    "f_n": ("Hz", "linear natural frequency, coil open-circuit (omega_n = 2 pi f_n)"),
    "zeta": ("-", "mechanical damping ratio"),
    "c3": ("1/(m^2 s^2)", "cubic stiffness per unit mass"),
    "c5": ("1/(m^4 s^2)", "quintic stiffness per unit mass"),
    "c7": ("1/(m^6 s^2)", "septic stiffness per unit mass"),
    "c_A": ("-", "base-acceleration participation factor"),
    "mass": ("kg", "modal mass m"),
    "theta": ("N/A = V s/m", "electromechanical coupling"),
    "R": ("ohm", "coil + load resistance"),
    "L": ("H", "coil inductance"),
    "shaker_limit": ("m/s^2", "largest base acceleration the shaker makes"),
}

FLUTTER_V_MAX = 26.0
SCURVE_FREQS = (20.0, 21.0, 22.0, 23.0, 24.0, 25.0, 26.0)
PLOT_FREQS = (20.0, 22.0, 24.0, 26.0)


def _param_table(params, units: dict) -> str:
    names = [f.name for f in fields(params)]
    missing = set(names) ^ set(units)
    if missing:
        raise SystemExit(f"make_physics_figures: units table out of date for {sorted(missing)}")
    rows = ["| symbol | value | unit | meaning |", "|---|---|---|---|"]
    for n in names:
        u, what = units[n]
        rows.append(f"| `{n}` | {getattr(params, n):g} | {u} | {what} |")
    return "\n".join(rows)


def _segments(x, y, stable):
    """Split a branch into runs of equal stability, each run sharing its end points."""
    out, start = [], 0
    for k in range(1, len(x) + 1):
        if k == len(x) or stable[k] != stable[start]:
            stop = min(k + 1, len(x))
            out.append((x[start:stop], y[start:stop], bool(stable[start])))
            start = k
    return out


def flutter_figure(branch, path: Path) -> None:
    V_h, f_h = branch.hopf
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.3))
    # prepend the Hopf point (zero amplitude) to the orbit branch
    V = np.concatenate([[V_h], branch.V])
    h = np.concatenate([[0.0], branch.heave_amp]) * 1e3
    a = np.rad2deg(np.concatenate([[0.0], branch.pitch_amp]))
    st = np.concatenate([[branch.stable[0]], branch.stable])
    V_lo = min(branch.V.min(), branch.folds[0]["V"] if branch.folds else V_h) - 1.0
    for ax, y, lab in ((ax1, h, "heave first-harmonic amplitude (mm)"),
                       (ax2, a, "pitch first-harmonic amplitude (deg)")):
        for xs, ys, s in _segments(V, y, st):
            ax.plot(xs, ys, "-" if s else "--", color="C0" if s else "C3", lw=2,
                    label="stable LCO" if s else "unstable LCO")
        ax.plot([V_lo, V_h], [0, 0], "-", color="k", lw=2, label="stable equilibrium")
        ax.plot([V_h, FLUTTER_V_MAX], [0, 0], "--", color="k", lw=1.5,
                label="unstable equilibrium")
        ax.plot([V_h], [0], "o", color="k", ms=7, label=f"Hopf {V_h:.3f} m/s, {f_h:.3f} Hz")
        for f in branch.folds:
            yv = f["heave_amp"] * 1e3 if ax is ax1 else np.rad2deg(f["pitch_amp"])
            ax.plot([f["V"]], [yv], "s", color="C2", ms=7,
                    label=f"fold {f['V']:.3f} m/s")
        ax.set_xlim(V_lo, FLUTTER_V_MAX)
        ax.set_xlabel("airspeed V (m/s)")
        ax.set_ylabel(lab)
        ax.grid(alpha=0.3)
    handles, labels = ax1.get_legend_handles_labels()
    uniq = dict(zip(labels, handles))
    ax1.legend(uniq.values(), uniq.keys(), loc="upper left", fontsize=8)
    fig.suptitle("Flutter aerofoil (unsteady 2+1 DoF model): true limit-cycle branch")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def oscillator_figure(curves: dict, params: OscillatorParams, path: Path) -> None:
    fig, ax = plt.subplots(figsize=(8, 5))
    for i, f in enumerate(PLOT_FREQS):
        c = curves[f]
        col = f"C{i}"
        for xs, ys, s in _segments(c.Phi, c.amp * 1e3, c.stable):
            ax.plot(xs, ys, "-" if s else "--", color=col, lw=2 if s else 1.5,
                    label=f"{f:g} Hz" if s and xs[0] == c.Phi[0] else None)
        for fo in c.folds:
            ax.plot([fo["Phi"]], [fo["amp"] * 1e3], "o", color=col, mfc="white", ms=6)
    ax.axvline(params.shaker_limit, color="grey", lw=1, ls=":")
    ax.text(params.shaker_limit * 0.97, 0.3, "shaker limit", rotation=90, ha="right",
            va="bottom", color="grey", fontsize=8)
    ax.plot([], [], "-", color="k", label="stable")
    ax.plot([], [], "--", color="k", label="unstable")
    ax.plot([], [], "o", color="k", mfc="white", label="fold")
    ax.set_xscale("log")
    ax.set_xlim(0.3, params.shaker_limit * 1.15)
    ax.set_ylim(0, None)
    ax.set_xlabel(r"base-acceleration amplitude $\Phi$ (m/s$^2$, log scale)")
    ax.set_ylabel("displacement first-harmonic amplitude (mm)")
    ax.set_title("Electrodynamic oscillator (with coil): true S-curves at fixed frequency")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


PAGE_TEMPLATE = r"""# Rig physics (ground truth)

*Generated by `docs/make_physics_figures.py` from `rig_sim.physics`; edit the script, not
this page.* These models are hidden from every client: the CBC host sees only the register
map, and the fitting side only the logged data. The numbers below are the rigs' own truth,
computed by `rig_sim.physics.truth` (the reference the campaign tests judge against).

**Amplitude** everywhere means the *first-harmonic amplitude* $\sqrt{{a_1^2+b_1^2}}$ of the
Fourier series of the coordinate over one period (heave $h$ for the aerofoil, tip
displacement $x$ for the oscillator).

## Flutter aerofoil (2+1 DoF, unsteady aerodynamics)

Paper appendix A.1, as implemented in `rig_sim/physics/flutter.py` and
`rig_sim/physics/rhs.py`:

$$\mathbf M\ddot{{\mathbf q}} + \mathbf B(V)\dot{{\mathbf q}} + \mathbf S(V)\mathbf q
 + \mathbf f_{{NL}}(\mathbf q) = \mathbf F,\qquad
\mathbf q = (h,\ \alpha,\ w),\quad
\mathbf f_{{NL}} = (0,\ k_{{\alpha2}}\alpha^2 + k_{{\alpha3}}\alpha^3,\ 0),\quad
\mathbf F = (F_{{\rm heave}},\ M_{{\rm pitch}},\ 0)$$

$h$ heave (m), $\alpha$ pitch (rad), $w$ the aerodynamic lag state of the Sears/Jones
approximation of Theodorsen's function; $V$ the airspeed (m/s). With
$C = c_0 - c_1 - c_3$, $D = c_1c_2 + c_3c_4$, $S_w = m_w x_\alpha b$ (the paper's
$m_w(b-x_f)$):

$$\mathbf M = \begin{{pmatrix}} m_T + \rho\pi b^2 & S_w - \rho\pi b^3 a & 0\\
S_w - \rho\pi b^3 a & I_\alpha + \rho\pi b^4(\tfrac18 + a^2) & 0\\ 0 & 0 & 1\end{{pmatrix}}$$

$$\mathbf B = \begin{{pmatrix}}
c_h + 2\pi\rho bVC & \rho\pi b^2V + 2\pi\rho b^2V(\tfrac12-a)C & 2\pi\rho V^2bD\\
-2\pi\rho b^2V(a+\tfrac12)C & c_\alpha + \rho\pi b^3V(\tfrac12-a) - 2\pi\rho b^3V(\tfrac12-a)(\tfrac12+a)C & -2\pi\rho b^2V^2(a+\tfrac12)D\\
-\tfrac1b & -(\tfrac12-a) & (c_2+c_4)\tfrac Vb\end{{pmatrix}}$$

$$\mathbf S = \begin{{pmatrix}}
k_h & 2\pi\rho bV^2C & 2\pi\rho V^3c_2c_4(c_1+c_3)\\
0 & k_\alpha - 2\pi\rho b^2V^2(\tfrac12+a)C & -2\pi\rho b^2V^3(\tfrac12+a)c_2c_4(c_1+c_3)\\
0 & -\tfrac Vb & c_2c_4\tfrac{{V^2}}{{b^2}}\end{{pmatrix}}$$

The actuator (control force) acts on heave; process noise is a random pitch moment.

{flutter_table}

### Truth

| quantity | value |
|---|---|
| Hopf point (rest loses stability) | V = {V_h:.4f} m/s, f = {f_h:.4f} Hz |
| Hopf type | subcritical (unstable limit cycles for V below the Hopf point) |
| fold of limit cycles | V = {V_f:.4f} m/s, heave amplitude {A_f:.2f} mm, pitch amplitude {P_f:.2f} deg, f = {F_f:.4f} Hz |
| bistable window | {V_f:.3f} m/s < V < {V_h:.3f} m/s (rest and a large LCO both stable) |

{flutter_amp_table}

![flutter truth](img/flutter_truth.png)

Stable orbits solid, unstable dashed; the equilibrium line is solid where rest is stable.

## Electrodynamic oscillator (shaker-driven cantilever with a coil)

As in `rig_sim/physics/oscillator.py` (per unit modal mass; $x$ the tip displacement
relative to the base, $i$ the coil current):

$$\ddot x = -2\zeta\omega_n\dot x - \omega_n^2x - c_3x^3 - c_5x^5 - c_7x^7
 + \frac{{\theta}}{{m}}\,i + c_A\,a_b(t),\qquad L\,\dot i = -R\,i - \theta\,\dot x$$

$a_b(t)$ is the total base acceleration: the host's forcing $\Phi\cos\omega t$ plus the
embedded controller's output. The coil circuit is the hidden physics (the mechanistic
model, a 7th-order Duffing oscillator, leaves it out). Through it the tip feels a
frequency-dependent damping $\theta^2R/(m(R^2+\omega^2L^2))$ and stiffening
$\theta^2\omega^2L/(m(R^2+\omega^2L^2))$, so one set of Duffing coefficients fits one
forcing frequency only.

{osc_table}

Equivalent coil damping and stiffness (per unit mass) over the forcing band, against the
mechanical $2\zeta\omega_n$ = {c_mech:.3f} 1/s and $\omega_n^2$ = {k_mech:.1f} 1/s²:

{coil_table}

### Truth: S-curves at fixed frequency

Continuation in $\Phi$ of the forced periodic orbits (period $1/f$) of the full 3-state
system. At every frequency from 20 to 26 Hz the curve has two folds below the shaker
limit and an unstable middle branch:

{fold_table}

![oscillator truth](img/oscillator_truth.png)

Stable orbits solid, unstable dashed, folds as open circles.

## How the truth is computed

`rig_sim/physics/truth/`: shooting on the compiled right-hand sides (fixed-step RK4,
{n_fl} steps per period for the aerofoil and {n_os} for the oscillator; halving the step
changes amplitudes and fold locations by less than 1e-8 relative), Jacobians and monodromy
matrices by central differences, pseudo-arclength continuation in scaled unknowns, Floquet
multipliers for stability (for the autonomous aerofoil, the trivial multiplier 1 is
excluded; the period is an unknown with the phase condition $\dot h(0) = 0$), and folds
located by a root find on the parameter component of the branch tangent. The tests in
`tests/test_physics_truth.py` check the result against published values of the Hopf point
and against direct adaptive (DOP853) time simulation.
"""


def main() -> None:
    IMG.mkdir(parents=True, exist_ok=True)
    fp, op = FlutterParams(), OscillatorParams()

    V_h, f_h = flutter_hopf(fp)
    branch = flutter_lco_branch(fp, V_max=FLUTTER_V_MAX)
    if len(branch.folds) != 1:
        raise SystemExit(f"expected one fold on the flutter branch, found {len(branch.folds)}")
    fold = branch.folds[0]
    flutter_figure(branch, IMG / "flutter_truth.png")

    rows = ["| V (m/s) | stable LCO heave amp. (mm) | unstable LCO heave amp. (mm) |",
            "|---|---|---|"]
    for V in (17.0, 18.0, 19.0, 20.0, 21.0, 22.0, 23.0, 23.5, 24.0, 25.0, 26.0):
        r = flutter_lco_at(V, branch)
        fmt = (lambda x: "—" if x is None else f"{x * 1e3:.3f}")
        rows.append(f"| {V:g} | {fmt(r['stable'])} | {fmt(r['unstable'])} |")
    flutter_amp_table = "\n".join(rows)

    curves = {f: oscillator_scurve(f, op, ds_max=0.1) for f in SCURVE_FREQS}  # dense for plots
    oscillator_figure(curves, op, IMG / "oscillator_truth.png")
    rows = ["| f (Hz) | jump-up fold Φ (m/s²) | amp. there (mm) | jump-down fold Φ (m/s²) "
            "| amp. there (mm) |", "|---|---|---|---|---|"]
    for f, c in curves.items():
        if len(c.folds) != 2:
            raise SystemExit(f"{f} Hz: expected two folds, found {len(c.folds)}")
        hi, lo = c.folds
        rows.append(f"| {f:g} | {hi['Phi']:.3f} | {hi['amp'] * 1e3:.3f} | {lo['Phi']:.3f} "
                    f"| {lo['amp'] * 1e3:.3f} |")
    fold_table = "\n".join(rows)

    rows = ["| f (Hz) | coil damping (1/s) | coil stiffness (1/s²) |", "|---|---|---|"]
    for f in SCURVE_FREQS:
        d, k = op.coil_damping_and_stiffness(2 * np.pi * f)
        rows.append(f"| {f:g} | {d:.3f} | {k:.1f} |")
    coil_table = "\n".join(rows)

    page = PAGE_TEMPLATE.format(
        flutter_table=_param_table(fp, FLUTTER_UNITS),
        osc_table=_param_table(op, OSCILLATOR_UNITS),
        V_h=V_h, f_h=f_h, V_f=fold["V"], A_f=fold["heave_amp"] * 1e3,
        P_f=np.rad2deg(fold["pitch_amp"]), F_f=1.0 / fold["period"],
        flutter_amp_table=flutter_amp_table, fold_table=fold_table, coil_table=coil_table,
        c_mech=2 * op.zeta * op.omega_n, k_mech=op.omega_n**2,
        n_fl=branch.n_steps, n_os=curves[SCURVE_FREQS[0]].n_steps,
    )
    PAGE.write_text(page, encoding="utf-8")
    print(f"wrote {IMG / 'flutter_truth.png'}, {IMG / 'oscillator_truth.png'}, {PAGE}")


if __name__ == "__main__":
    main()
