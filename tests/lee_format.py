"""The simulated aerofoil's CBC points written as wind-tunnel files: the lee2020 layout
(MATLAB v5, one point per file, the lab's file names), so that the default command a
researcher types on real data can be tried on a rig configuration whose truth is known and
that nothing in ``ude_fit`` was ever run on.

Each point is the rig's own board held on a true orbit of the configured rig (its PD
controller, the truth orbit as the target, process and sensor noise on), recorded at the
board's rate, and written as the wind-tunnel files hold their channels:

* row 0: heave in the sensor's volts (:data:`HEAVE_M_PER_V`, the sensitivity the files come
  with) about a DC offset;
* row 1: the control target, in the same volts;
* row 2: the actuator signal in volts (the force over :data:`ACTUATOR_N_PER_V`, a gain the
  files do not carry, as the real ones do not);
* row 3: pitch in rad about an encoder offset, with bursts of failed reads at the
  encoder's all-ones code (the real files lose 2-22 % of their pitch samples so);
* row 4: a constant channel.

The offsets, the gain and the dropout rate are the layout's, not the physics': the loader
must remove or ignore each of them.
"""

from __future__ import annotations

import math
import os

import numpy as np
import scipy.io

from rig_sim.firmware.board import SPECS
from tests.ude_fixtures import flutter_branch, flutter_truth_orbits, run_board_on_orbit

HEAVE_M_PER_V = 0.18              # the wind-tunnel heave sensor's sensitivity (lee2020 README)
HEAVE_OFFSET_V = 3.3              # the sensor's DC level
PITCH_OFFSET_RAD = 0.35           # the encoder's zero is not the rig's
ENCODER_FAILED_READ = 2 * math.pi * (1 - 2.0 ** -20)   # the 20-bit encoder's all-ones code
ACTUATOR_N_PER_V = 10.0           # actuator gain (unknown to the loader)
RECORD_S = 20.0                   # seconds per point, as the wind-tunnel records
# a point whose recorded heave's first harmonic is off its target's by more than this
# fraction was not held (a CBC run would not accept it): the board's noise is absolute,
# sized on the design rig's orbits, and on a rig with much smaller ones it can knock a
# weakly attracting orbit off the hold (the response then decays to rest whatever the
# target says)
HOLD_TOLERANCE = 0.2


def point_airspeeds(hopf: float, fold: float, n: int = 7) -> np.ndarray:
    """``n`` airspeeds across the bistable range, from a quarter of the way above the fold to
    just below the Hopf point (where a CBC campaign finds both orbits well apart)."""
    span = hopf - fold
    return np.linspace(fold + 0.25 * span, hopf - 0.08 * span, n)


TRUTH_V_MAX = 40.0                # m/s: the truth branch traced up to here
# the largest target error write_lee_campaign takes: a target half the orbit off is no
# longer a CBC point near it
TARGET_ERROR_MAX = 0.5


def truth_of(physics: tuple) -> dict:
    """The configured rig's Hopf and fold airspeeds (its own continuation)."""
    branch = flutter_branch(TRUTH_V_MAX, (), None, tuple(physics))
    if branch.hopf is None or len(branch.folds) != 1:
        raise ValueError(f"rig configuration {physics}: needs a subcritical Hopf point and "
                         f"one fold (Hopf {branch.hopf}, {len(branch.folds)} folds)")
    return {"hopf": float(branch.hopf[0]), "fold": float(branch.folds[0]["V"])}


def _dropouts(n: int, fraction: float, rng) -> np.ndarray:
    """A mask of failed encoder reads: bursts of 15 samples covering ``fraction`` of ``n``."""
    bad = np.zeros(n, dtype=bool)
    burst = 15
    for start in rng.choice(max(n - burst, 1), size=int(fraction * n / burst), replace=False):
        bad[start:start + burst] = True
    return bad


def held_fractions(ts: dict, amplitude: float, blocks: int = 4) -> np.ndarray:
    """The recorded heave's first harmonic (at the board's locked phase) over the target's
    set ``amplitude``, in each of ``blocks`` parts of the record: all 1 where the point
    was held throughout."""
    turn = np.exp(-1j * ts["phase"])
    return np.array([2.0 * abs(np.mean((x - x.mean()) * e)) / amplitude
                     for x, e in zip(np.array_split(ts["x"], blocks),
                                     np.array_split(turn, blocks))])


def write_point(path, airspeed: float, ts: dict, frequency: float, rng,
                dropout: float) -> None:
    heave = ts["x"] / HEAVE_M_PER_V + HEAVE_OFFSET_V
    target = ts["target"] / HEAVE_M_PER_V + HEAVE_OFFSET_V
    control = ts["control"] / ACTUATOR_N_PER_V
    pitch = ts["q2"] + PITCH_OFFSET_RAD
    pitch = np.where(_dropouts(pitch.size, dropout, rng), ENCODER_FAILED_READ, pitch)
    data = np.vstack([heave, target, control, pitch, np.full(heave.size, HEAVE_OFFSET_V)])
    t = np.arange(heave.size) / SPECS["flutter"].rate_hz    # the board's own sample rate
    scipy.io.savemat(str(path), {"data": data, "time": t[None, :],
                                 "Wind_sped": float(airspeed),
                                 "freq_actual": float(frequency)})


def write_lee_campaign(folder, physics: tuple, *, sigma: float, seed: int, n_speeds: int = 7,
                       n_stable: int = 4, dropout: float = 0.1,
                       record_s: float = RECORD_S, airspeed_error: float = 0.0,
                       target_error: float = 0.0) -> dict:
    """The configured rig's CBC points as wind-tunnel files in ``folder``: the unstable orbit
    at each of ``n_speeds`` airspeeds (:func:`point_airspeeds`), the stable one at the lowest
    ``n_stable`` of them, named as the lab names them (CBC_stable_v20_7.mat,
    CBC_unstable_v21_6.mat). ``airspeed_error`` (m/s): each file's recorded airspeed is the
    one its orbit was held at plus a normal error of that standard deviation, drawn anew
    per point (a tunnel's speed reading, and the air's density drifting between points,
    are never exact; the points then scatter about the rig's branches as measured ones
    do). ``target_error``: each point's control target is its orbit's amplitude times 1 plus
    a normal error of that standard deviation, so that the control holds an orbit of the
    controlled system a little off the open-loop one (a CBC search stopped at its tolerance:
    the lee2020 files' control has a first harmonic at every point). Returns the truth: Hopf,
    fold, and per file its orbit's airspeed, the recorded one, the target's scale, its
    stability and heave amplitude."""
    if not airspeed_error >= 0:
        raise ValueError(f"airspeed_error must be 0 or more m/s, not {airspeed_error}")
    if not 0 <= target_error < TARGET_ERROR_MAX:
        raise ValueError(f"target_error must be a fraction in [0, {TARGET_ERROR_MAX}), "
                         f"not {target_error}")
    os.makedirs(folder, exist_ok=True)
    ref = truth_of(physics)
    speeds = point_airspeeds(ref["hopf"], ref["fold"], n_speeds)
    orbits = flutter_truth_orbits(tuple(float(v) for v in speeds), (), None, tuple(physics),
                                  v_max=TRUTH_V_MAX)
    kinds = sorted((round(tr["parameter"], 9), tr["stable"]) for tr in orbits)
    expected = sorted((round(float(v), 9), st) for v in speeds for st in (False, True))
    if kinds != expected:
        raise ValueError(f"rig configuration {physics}: not one stable and one unstable orbit "
                         f"at each airspeed of {np.round(speeds, 2).tolist()}")
    rng = np.random.default_rng(seed)
    # its own stream, so that a campaign without the error is the one it always was
    speed_rng = np.random.default_rng([seed, 1])
    target_rng = np.random.default_rng([seed, 2])
    points = []
    for i, tr in enumerate(orbits):
        k = int(np.argmin(np.abs(speeds - tr["parameter"])))
        if tr["stable"] and k >= n_stable:
            continue
        scale = 1.0 + (target_rng.normal(0.0, target_error) if target_error > 0 else 0.0)
        ts, _, f_est = run_board_on_orbit("flutter", tr, sigma=sigma, seed=seed + i,
                                          record_s=record_s, physics=tuple(physics),
                                          target_scale=scale)
        kind = "stable" if tr["stable"] else "unstable"
        # held: the response against the target it was held at, not the open-loop orbit's
        # amplitude (off target the control moves the response off the orbit: a stable one
        # part of the way to the target, an unstable one past it)
        held = held_fractions(ts, tr["amplitude"] * scale)
        if np.any(np.abs(held - 1.0) > HOLD_TOLERANCE):
            raise ValueError(f"rig configuration {physics}, sigma {sigma}: the {kind} orbit "
                             f"at {tr['parameter']:.2f} m/s was not held (response "
                             f"{np.round(held, 2).tolist()} of the target in the record's "
                             "quarters); try less noise")
        recorded = tr["parameter"] + (speed_rng.normal(0.0, airspeed_error)
                                      if airspeed_error > 0 else 0.0)
        name = f"CBC_{kind}_v{recorded:.1f}".replace(".", "_") + ".mat"
        if any(p["file"] == name for p in points):
            raise ValueError(f"airspeeds {np.round(speeds, 2).tolist()}: two round to {name} "
                             "(the lab's names hold 0.1 m/s)")
        write_point(os.path.join(folder, name), recorded, ts, f_est, rng, dropout)
        points.append({"file": name, "airspeed": tr["parameter"], "recorded": recorded,
                       "target_scale": scale, "stable": tr["stable"],
                       "amplitude": tr["amplitude"]})
    return {**ref, "physics": list(physics), "sigma": sigma, "seed": seed, "points": points}
