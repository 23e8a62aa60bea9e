"""Campaign files whose points are the rigs' TRUE periodic orbits, for the ude_fit tests.

The orbits come from rig_sim's own truth analysis (shooting + continuation of the very
right-hand sides the firmware integrates), so a loader or a fit can be judged against
numbers that are right by construction. The files are written by the campaign writer
itself (cbc_controller.log.CampaignWriter), document by document as a campaign would.

Two flavours:
* noise-free (sigma = 0, no record): each point's Fourier means are the truth orbit's
  coefficients, computed from one period integrated with the truth's own step count;
* with raw records (sigma > 0, or record_s > 0): the rig's board is held on the truth
  orbit by its PD controller, with the truth orbit as the target, and `record_s` seconds
  of full-rate ring samples are logged after settling, with the board's Fourier means,
  as a campaign does. Flutter runs phase-locked (target A0 + A1 cos phi, as the
  wind-tunnel campaign did); the oscillator runs on the forcing phase, with the host
  forcing set to the truth's Phi and the truth's 15 coefficients as the target.

Everything is seeded; the truth continuation is cached per process (it takes seconds).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from cbc_controller.log import CampaignWriter
from rig_sim.device import register_map as M
from rig_sim.firmware import layout as L
from rig_sim.firmware.board import Board, RigOptions
from rig_sim.physics.configuration import configured_params
from rig_sim.physics.flutter import flutter_kernel_params
from rig_sim.physics.oscillator import OscillatorParams, oscillator_kernel_params
from rig_sim.physics.rhs import flutter_deriv, oscillator_deriv
from rig_sim.physics.truth import (flutter_lco_branch, flutter_orbit_at, oscillator_orbit_at,
                                   oscillator_scurve)

NH = 7
NCOEF = 2 * NH + 1
CHANNELS = ("response", "control", "excitation", "second")
CHANNEL_INDEX = {"response": L.CH_RESPONSE, "control": L.CH_CONTROL,
                 "excitation": L.CH_EXCITATION, "second": L.CH_SECOND}
DEFAULT_AIRSPEEDS = (18.0, 20.0, 22.0, 23.0, 24.5, 25.5)   # m/s: 4 bistable, 2 above Hopf
DEFAULT_FREQS = (23.0,)                                    # Hz
STARTED = "2025-01-01T00:00:00+00:00"                      # fixed: files are reproducible
TRUTH_METHOD = "truth: Floquet multipliers of the rig's own model (rig_sim.physics.truth)"

# the campaign plans' gains: they hold the unstable orbits of both rigs
FLUTTER_GAINS = (200.0, 60.0)          # kp N/m, kd N s/m (cbc_controller.plans.autonomous)
OSCILLATOR_GAINS = (1.0e4, 50.0)       # kp 1/s^2, kd 1/s (cbc_controller.plans.forced)
SETTLE_S = {"flutter": 2.0, "oscillator": 0.5}
# a target held off the open-loop orbit (invasive): the rig moves to an orbit of the
# controlled system on the closed loop's slow time scale, so the board is settled until the
# response stops moving (what a CBC plan waits for before it logs a point)
STEADY_REL = 1e-4                      # first-harmonic change between blocks, relative
STEADY_SE = 2.0                        # ... or within this many standard errors (noise)
MAX_STEADY_S = 120.0                   # rig seconds; a hold that is still moving is an error
DEFAULT_RECORD_S = {"flutter": 4.0, "oscillator": 1.0}


# ---- truth, cached --------------------------------------------------------------------------

START_FROM_CLEAN = ("freeplay", "heave_friction", "pitch_friction")


@lru_cache(maxsize=8)
def flutter_branch(V_max: float = 26.0, effects: tuple = (), plugin: str | None = None,
                   physics: tuple = ()):
    """The truth branch; ``effects``: ("name=value", ...) the rig is started with,
    ``plugin`` its --effect-plugin spec (FILE.py:FUNC; it must vanish to first order at
    rest) and ``physics`` its --physics ("name=value", ...: another configuration).
    Effects that change rest itself (no usable Hopf point) start from the effect-free
    branch's stable orbit at 24 m/s (see flutter_lco_branch's start_V)."""
    start = 24.0 if any(e.split("=")[0] in START_FROM_CLEAN for e in effects) else None
    func = None
    if plugin:
        from rig_sim.physics.effects import load_plugin
        func = load_plugin(plugin)
    return flutter_lco_branch(configured_params("flutter", physics), V_max=V_max,
                              effects=list(effects) or None, start_V=start, plugin=func)


@lru_cache(maxsize=16)
def oscillator_curve(freq_hz: float, effects: tuple = (), plugin: str | None = None):
    """The truth S-curve at one frequency; ``plugin``: the rig's --effect-plugin spec (a
    force (F,) in N that vanishes at rest)."""
    func = None
    if plugin:
        from rig_sim.physics.effects import load_plugin
        func = load_plugin(plugin)
    return oscillator_scurve(freq_hz, effects=list(effects) or None, plugin=func)


def series_of_samples(H: np.ndarray) -> np.ndarray:
    """(n_coord, 15) coefficients a0, a1..a7, b1..b7 of samples H (n, n_coord) taken at the
    phases 2 pi j / n over one period."""
    n = H.shape[0]
    c = np.fft.rfft(H, axis=0) / n
    out = np.empty((H.shape[1], NCOEF))
    out[:, 0] = c[0].real
    out[:, 1:NH + 1] = 2.0 * c[1:NH + 1].real.T
    out[:, NH + 1:] = -2.0 * c[1:NH + 1].imag.T
    return out


def _rk4_period(deriv, y0: np.ndarray, T: float, n: int, drive=None) -> np.ndarray:
    """States at t = j T / n, j = 0..n-1, by n classical RK4 steps (the truth's scheme and
    step count, so the samples are the truth's own). drive(t) -> the base acceleration."""
    y = np.array(y0, dtype=float)
    dt = T / n
    H = np.empty((n, y.size))
    k1, k2, k3, k4 = (np.empty_like(y) for _ in range(4))
    for j in range(n):
        H[j] = y
        t = j * dt
        deriv(y, k1, t)
        deriv(y + 0.5 * dt * k1, k2, t + 0.5 * dt)
        deriv(y + 0.5 * dt * k2, k3, t + 0.5 * dt)
        deriv(y + dt * k3, k4, t + dt)
        y = y + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return H


def flutter_truth_orbits(airspeeds, effects: tuple = (), plugin: str | None = None,
                         physics: tuple = (), v_max: float | None = None) -> list[dict]:
    """Every truth orbit at each airspeed: dicts with parameter, frequency, stable,
    amplitude, coeffs (2, 15) (heave m, pitch rad; phase origin at the heave extremum the
    truth starts from), state, period, floquet_max, pitch_amp, heave_dc. ``v_max``: the
    airspeed the truth branch is traced up to (default 26 m/s or just above the highest
    airspeed; a configuration whose Hopf point lies higher needs more)."""
    V_max = max(26.0, float(np.max(airspeeds)) + 0.5) if v_max is None else v_max
    branch = flutter_branch(V_max, tuple(effects), plugin, tuple(physics))
    E = branch.effects
    force = branch._problem.plugin
    out = []
    for V in airspeeds:
        Kp = flutter_kernel_params(configured_params("flutter", physics), float(V))
        for orb in flutter_orbit_at(float(V), branch):
            def deriv(y, dy, t):
                f = (0.0, 0.0) if force is None else force(0.0, y[0:2].copy(),
                                                           y[3:5].copy(), None)
                flutter_deriv(y, dy, f[0], f[1], Kp, E)
            H = _rk4_period(deriv, orb["state"], orb["period"], branch.n_steps)
            out.append(dict(parameter=float(V), frequency=1.0 / orb["period"],
                            stable=bool(orb["stable"]), amplitude=orb["heave_amp"],
                            pitch_amp=orb["pitch_amp"], heave_dc=orb["heave_dc"],
                            coeffs=series_of_samples(H[:, [0, 1]]), forcing=None,
                            state=orb["state"], period=orb["period"],
                            floquet_max=orb["floquet_max"]))
    return out


def oscillator_forcings(curve, per_freq: int) -> list[float]:
    """Forcing amplitudes covering the S-curve: one below the jump-down fold (one stable
    orbit), per_freq - 2 between the folds (three orbits each: both stable branches and
    the unstable middle), one above the jump-up fold."""
    folds = sorted(f["Phi"] for f in curve.folds)
    if len(folds) != 2 or per_freq < 3:
        lo, hi = float(curve.Phi.min()), float(curve.Phi.max())
        return list(np.linspace(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo), max(per_freq, 1)))
    lo, hi = folds
    inside = lo + (hi - lo) * np.arange(1, per_freq - 1) / (per_freq - 1)
    return [0.5 * lo, *map(float, inside), 1.5 * hi]


def oscillator_truth_orbits(freqs, per_freq: int, effects: tuple = (),
                            plugin: str | None = None) -> list[dict]:
    """Truth orbits of the forced oscillator: dicts with parameter (Phi, m/s^2), frequency,
    stable, amplitude, coeffs (1, 15) and forcing (15,) = Phi cos(phi), both in the frame
    of the truth (t = 0 where the forcing Phi cos(w t) peaks), state, floquet_max."""
    p = OscillatorParams()
    Kp = oscillator_kernel_params(p)
    out = []
    for f in freqs:
        curve = oscillator_curve(float(f), tuple(effects), plugin)
        force = curve._problem.plugin
        w = 2.0 * math.pi * float(f)

        def deriv(y, dy, t, Phi):
            F = 0.0 if force is None else force(t, y[0:1].copy(), y[1:2].copy(), None)[0]
            oscillator_deriv(y, dy, Phi * math.cos(w * t), F, Kp, curve.effects, p.mass)
        for Phi in oscillator_forcings(curve, per_freq):
            for orb in oscillator_orbit_at(Phi, curve):
                H = _rk4_period(lambda y, dy, t, Phi=Phi: deriv(y, dy, t, Phi),
                                orb["state"], 1.0 / float(f), curve.n_steps)
                forcing = np.zeros(NCOEF)
                forcing[1] = Phi
                out.append(dict(parameter=float(Phi), frequency=float(f),
                                stable=bool(orb["stable"]), amplitude=orb["amp"],
                                coeffs=series_of_samples(H[:, [0]]), forcing=forcing,
                                state=orb["state"], floquet_max=orb["floquet_max"]))
    return out


# ---- the board held on a truth orbit ------------------------------------------------------------

def _decode_ring(board: Board, rec: np.ndarray) -> dict:
    """Ring records -> SI fields, decoded exactly as cbc_controller.client.pull_ring does."""
    counts = rec.view(np.int16).astype(float)
    spec = board.spec
    fs = {"x": spec.full_scale[0], "x_dot": spec.full_scale[1], "q2": spec.full_scale[2],
          "q2_dot": spec.full_scale[3], "target": spec.full_scale[0],
          "control": spec.saturation, "parameter": spec.param_full_scale}
    out = {name: counts[:, L.REC_X + i] / 32767.0 * fs[name]
           for i, name in enumerate(("x", "x_dot", "q2", "q2_dot", "target", "control",
                                     "parameter"))}
    out["phase"] = counts[:, L.REC_PHASE] / 32767.0 * np.pi + np.pi
    return out


def _set_targets(board: Board, coeffs) -> None:
    names = ["target_a0"] + [f"target_a{k}" for k in range(1, NH + 1)] \
        + [f"target_b{k}" for k in range(1, NH + 1)]
    for name, c in zip(names, coeffs):
        board.set(name, float(c))


def run_board_on_orbit(system: str, truth: dict, *, sigma: float, seed: int,
                       record_s: float, effects: tuple = (),
                       plugin: str | None = None, target_scale: float = 1.0,
                       physics: tuple = ()) -> tuple[dict, dict, float]:
    """Hold the board on a truth orbit; returns (timeseries, fourier {ch: mean, var},
    board frequency estimate). ``target_scale`` (flutter): the target's amplitude is the
    truth's times this, so that the board holds an orbit of the controlled system instead
    (what a CBC point accepted with loose tolerances is). ``physics``: the rig's --physics."""
    b = Board(RigOptions(kind=system, sigma=sigma, seed=seed, effects=list(effects),
                         plugin=plugin, physics=list(physics)))
    if system == "flutter":
        kp, kd = FLUTTER_GAINS
        b.set("parameter", truth["parameter"])
        b.set("frequency", truth["frequency"])
        b.set("phase_mode", 1.0)
        target = np.zeros(NCOEF)
        target[0] = truth["coeffs"][0, 0]
        target[1] = truth["amplitude"] * target_scale
    else:
        kp, kd = OSCILLATOR_GAINS
        b.set("parameter", truth["parameter"])      # the host forcing Phi cos(forcing phase)
        b.set("frequency", truth["frequency"])
        b.set("phase_mode", 0.0)
        target = truth["coeffs"][0]
    b.set("kp", kp)
    b.set("kd", kd)
    _set_targets(b, target)
    # the truth state is the orbit at phase 0: the forcing peak (oscillator, th_force = 0 at
    # sample 0) or the heave extremum (flutter, where the locked phase is 0)
    b.set_true_state(truth["state"])
    b.arm()
    b.advance(int(round(SETTLE_S[system] * b.rate)))
    if target_scale != 1.0:
        _settle_until_steady(b, truth)
    chunk = L.RING_CAP - 96                 # read each block before the ring wraps over it
    n_total = int(round(record_s * b.rate))
    blocks, samples = [], []
    while n_total > 0:
        n = min(chunk, n_total)
        start = b.seq
        b.advance(n)
        head = int(b.ic[L.IC_RING_HEAD])
        blocks.append(b.ring[(head - n + np.arange(n)) % L.RING_CAP].copy())
        samples.append(np.arange(start, start + n, dtype=np.int64))
        n_total -= n
    if b.fault:
        raise RuntimeError(f"board fault {b.fault} while holding {truth}")
    ts = _decode_ring(b, np.concatenate(blocks))
    ts["sample"] = np.concatenate(samples)
    fourier = {ch: {"mean": b.cmean[CHANNEL_INDEX[ch]].copy(),
                    "var": b.cvar[CHANNEL_INDEX[ch]].copy()} for ch in CHANNELS}
    return ts, fourier, float(b.fmean[0])


def _settle_until_steady(b: Board, truth: dict) -> None:
    """Advance ``b`` by blocks of its averaging window (navg periods) until the response's
    first harmonic (over that window) has twice in a row moved between blocks by less than
    STEADY_REL of itself or STEADY_SE standard errors of the difference (noise), so that the
    window the point is read from holds one orbit, not the way to it."""
    navg = int(b.cfg[L.CFG_NAVG])

    def first_harmonic() -> tuple[float, float]:
        mean, var = b.cmean[L.CH_RESPONSE], b.cvar[L.CH_RESPONSE]
        se = math.sqrt(2.0 * max(var[1] + var[1 + NH], 0.0) / navg)
        return math.hypot(mean[1], mean[1 + NH]), se

    block = int(round(navg * b.rate / truth["frequency"]))
    waited, quiet = 0.0, 0
    previous, _ = first_harmonic()
    while quiet < 2:
        if waited > MAX_STEADY_S:
            raise RuntimeError(f"the board held off {truth} was still moving after "
                               f"{waited:.0f} rig seconds")
        b.advance(block)
        waited += block / b.rate
        now, se = first_harmonic()
        quiet = quiet + 1 if abs(now - previous) <= max(STEADY_REL * now, STEADY_SE * se) else 0
        previous = now


# ---- writing --------------------------------------------------------------------------------------

def identity(system: str) -> dict:
    from rig_sim.firmware.board import SPECS
    spec = SPECS[system]
    return {"model": spec.model, "firmware_version": 100, "map_version": M.MAP_VERSION,
            "rig_kind": 0 if system == "flutter" else 1, "sample_rate": spec.rate_hz,
            "ring_capacity": L.RING_CAP, "fs_x": spec.full_scale[0],
            "fs_x_dot": spec.full_scale[1], "fs_q2": spec.full_scale[2],
            "fs_q2_dot": spec.full_scale[3], "fs_control": spec.saturation,
            "fs_parameter": spec.param_full_scale}


def write_campaign(path, system: str, points: list[dict], *, seed: int = 0) -> None:
    """A campaign file from point documents (the engine's "point" documents), with the
    "start" and "stop" documents around them."""
    writer = CampaignWriter(str(path), durable=False)
    try:
        writer("start", {
            "campaign": {"campaign": {"name": f"{system} truth", "rig": system, "seed": seed}},
            "campaign_toml": f'[campaign]\nname = "{system} truth"\nrig = "{system}"\n',
            "identity": identity(system), "versions": {"tests": "ude_fixtures"},
            "rig_url": "truth://rig_sim.physics.truth", "started": STARTED,
            "command": ["tests/ude_fixtures.py"], "seed": seed})
        for doc in points:
            writer("point", doc)
        writer("stop", {"reason": "completed", "ended": STARTED, "loop": {}})
    finally:
        writer.close()


def _point_doc(i: int, system: str, truth: dict, fourier: dict, timeseries: dict,
               frequency: float, navg: int, host_forcing: float) -> dict:
    flutter = system == "flutter"
    amp = math.hypot(fourier["response"]["mean"][1], fourier["response"]["mean"][1 + NH])
    kind = "stable" if truth["stable"] else "unstable"
    key = (f"V={truth['parameter']:.3f}/{kind}/A={truth['amplitude']:.6f}" if flutter else
           f"f={truth['frequency']:.3f}/Phi={truth['parameter']:.4f}/A={truth['amplitude']:.6f}")
    settings = {"kp": (FLUTTER_GAINS if flutter else OSCILLATOR_GAINS)[0],
                "kd": (FLUTTER_GAINS if flutter else OSCILLATOR_GAINS)[1],
                "frequency": truth["frequency"], "navg": navg}
    if flutter:
        settings["airspeed"] = truth["parameter"]
    else:
        settings["forcing_amplitude"] = host_forcing
    return {
        "index": i, "key": key, "rig": system, "parameter": truth["parameter"],
        "parameter_name": "airspeed" if flutter else "forcing_amplitude",
        "frequency": frequency, "amplitude": amp, "stable": truth["stable"],
        "stability_method": TRUTH_METHOD, "status": "ok", "settings": settings,
        "fourier": fourier, "history": [], "rig_time": 0.0, "wall_time": 0.0,
        "timeseries": timeseries,
        "extra": {"truth_amplitude": truth["amplitude"], "truth_floquet_max": truth["floquet_max"]},
        "loop": {},
    }


def write_truth_campaign(path, system: str, *, airspeeds=None, freqs=None, per_freq=None,
                         sigma: float = 0.0, seed: int = 0, record_s=None,
                         keep_record: bool = True, effects: tuple = (),
                         plugin: str | None = None, held_within: float | None = None,
                         invasive: float = 0.0, physics: tuple = ()) -> list[dict]:
    """Write a campaign file of the rig's true periodic orbits; returns the truth records
    (one per point, in file order; see flutter_truth_orbits / oscillator_truth_orbits).

    flutter: every orbit at each of `airspeeds` (default DEFAULT_AIRSPEEDS).
    oscillator: at each of `freqs` (default 23 Hz), `per_freq` forcing amplitudes (default
    4) chosen by oscillator_forcings: one, three, ..., three, one orbits.
    Raw records are taken (board held on the orbit) when sigma > 0 or record_s > 0;
    record_s defaults to 4 s (flutter) or 1 s (oscillator) of rig time. keep_record=False
    stores only the board's Fourier means of such a run (as a campaign without records).
    effects: ("name=value", ...) catalogue effects the rig (and its truth) is started with;
    the campaign file does not mention them (they are undeclared physics). plugin: the
    rig's --effect-plugin FILE.py:FUNC (time-invariant, compilable by numba; the aerofoil's
    returns (heave force, pitch moment), the oscillator's (force on the tip,)).
    held_within: drop a point whose held response's first-harmonic amplitude is off the
    truth orbit's by more than this fraction (noise knocked the board off an orbit it
    could not hold: a CBC campaign would not log it as converged); returned records are
    then those of the points written.
    invasive (flutter): hold every point with its target's amplitude (1 + invasive) and
    (1 - invasive) times the truth's, alternately, so the control stays on (the campaign
    a CBC run with loose tolerances leaves); the board is settled on the controlled orbit
    before the point is read (it moves there in seconds: after the fixed settle alone
    the unstable points were read halfway, 2-14 % short of where they end); the records
    stay the open-loop truth.
    physics (flutter): the rig's --physics ("name=value", ...), another configuration that
    the truth and the board share.
    """
    effects = tuple(effects)
    if physics and system != "flutter":
        raise ValueError("physics: the aerofoil's only (the oscillator's truth takes none)")
    if system == "flutter":
        truths = flutter_truth_orbits(DEFAULT_AIRSPEEDS if airspeeds is None else airspeeds,
                                      effects, plugin, physics)
    elif system == "oscillator":
        truths = oscillator_truth_orbits(DEFAULT_FREQS if freqs is None else freqs,
                                         4 if per_freq is None else int(per_freq), effects,
                                         plugin)
    else:
        raise ValueError(f"system {system!r}: flutter or oscillator")
    if record_s is None:
        record_s = DEFAULT_RECORD_S[system] if sigma > 0 else 0.0
    docs, kept = [], []
    for i, tr in enumerate(truths):
        if record_s > 0:
            ts, fourier, f_est = run_board_on_orbit(system, tr, sigma=sigma, seed=seed + i,
                                                    record_s=record_s, effects=effects,
                                                    plugin=plugin, physics=physics,
                                                    target_scale=1 + invasive * (-1) ** i)
            freq = f_est if system == "flutter" else tr["frequency"]
            navg, host = 10, tr["parameter"]
            if not keep_record:
                ts = {}
            held = math.hypot(fourier["response"]["mean"][1], fourier["response"]["mean"][1 + NH])
            if held_within is not None and abs(held / tr["amplitude"] - 1) > held_within:
                continue
        else:
            ts, navg, host = {}, 1, 0.0
            resp = tr["coeffs"][0]
            if system == "flutter":
                fourier = {"response": resp, "second": tr["coeffs"][1],
                           "control": np.zeros(NCOEF), "excitation": np.zeros(NCOEF)}
            else:
                # the CBC plans run with no host forcing: the control is the whole excitation
                fourier = {"response": resp, "control": tr["forcing"],
                           "excitation": tr["forcing"], "second": np.zeros(NCOEF)}
            fourier = {ch: {"mean": np.asarray(v, float), "var": np.zeros(NCOEF)}
                       for ch, v in fourier.items()}
            freq = tr["frequency"]
        docs.append(_point_doc(len(docs), system, tr, fourier, ts, freq, navg, host))
        kept.append(tr)
    write_campaign(path, system, docs, seed=seed)
    return kept
