"""The dataset of periodic orbits, from campaign HDF5 files and the lee2020 wind-tunnel files.

Every orbit is kept as a truncated Fourier series over one period (``_fourier``: K = 7
harmonics, 15 coefficients per coordinate).

Noise is removed as the paper does: by least squares over the whole raw record (many
periods) at the orbit's frequency ("Fourier averaging"); the residual's RMS is kept as
the point's noise estimate.

Phase frames (the time origin of phi), chosen so orbits from any source compare directly:

* flutter (autonomous): any time shift of an orbit is the same orbit, so the origin is
  put where the heave's fundamental peaks: heave a1 = A > 0, b1 = 0. Pitch is shifted
  by the same angle, so the heave-pitch phase relation is kept.
* oscillator (forced): the excitation defines the frame. The board correlates the
  response and the total excitation against its own forcing phase (kernel.py: in
  forcing mode th = th_force, the ring's `phase` field records that same th, and the
  host forcing is `parameter` cos(th)); a campaign point's response and excitation
  are therefore in one frame. That frame is then shifted so that the total
  excitation's fundamental is +Phi cos(phi), i.e. t = 0 where the forcing peaks, the
  convention of a model driven by Phi cos(w t) (and of rig_sim's truth). `forcing`
  keeps the excitation's DC and higher harmonics (a non-invasive point has them near
  zero, but they are what actually drove the rig).

Units are SI throughout; the lee2020 heave is converted from volts at the edge
(0.18 m/V) and nothing else in ude_fit sees volts (``data.lee``).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from .._fourier import K, NCOEF, _basis, shift_phase
from .._systems import KINDS, SystemKind, system_kind
from .holding import Holding

COORDINATES = {name: k.coordinates for name, k in KINDS.items()}
PARAMETER_NAMES = {name: k.parameter for name, k in KINDS.items()}


class DataError(Exception):
    """Input that cannot become a dataset. The message is one line and names the file."""

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()))


def _check_file(path: str, allow_dir: bool = False) -> None:
    if not os.path.exists(path):
        raise DataError(f"{path}: no such file or directory")
    if os.path.isdir(path) and not allow_dir:
        raise DataError(f"{path}: is a directory, not a file")
    if not os.access(path, os.R_OK):
        raise DataError(f"{path}: not readable (permission denied)")


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split()) or type(e).__name__




def _frozen(a) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Orbit:
    """One periodic orbit.

    parameter: airspeed (m/s, flutter) or forcing amplitude (base acceleration, m/s^2,
      oscillator; the first-harmonic amplitude of the total excitation as the campaign
      reported it).
    frequency: Hz. stable: True/False, None if unknown.
    coeffs: (n_coord, 15); flutter (heave h [m], pitch alpha [rad]), oscillator (x [m],).
    forcing: oscillator only, (15,) coefficients of the total base-acceleration
      excitation (m/s^2) in the same phase frame as coeffs; None for flutter.
    noise: (n_coord,) RMS of the raw record's residual after the K-harmonic fit (same
      units as the coordinate); NaN where there was no raw record.
    periods: how many periods went into the average (NaN if unknown).
    source: "file.h5#key" or "file.mat".
    stability_from: where ``stable`` came from ("file name", "campaign attribute",
      "--stability RULE"; "" while unknown).
    holding: how invasive the control that held the orbit was (:class:`Holding`), None
      where the file does not record the control.
    control: flutter only, (15,) coefficients of the recorded holding control in the same
      phase frame as coeffs and in ``holding.control_unit`` (N on a simulated campaign,
      volts in the lee2020 files); None where the file does not record it. A fit may take
      it as a known input (``--control-input``); the oscillator's ``forcing`` already holds
      its control (the total excitation).
    sensor_means: (n_coord,) the orbit's means in the sensors' frame where the file does
      not record the rig's rest position (the lee2020 heave sensor's DC level, the pitch
      encoder's angle); ``coeffs`` are then about the orbit's own mean, until
      :func:`~ude_fit.training.sensor_zero.with_sensor_zero` puts them about the rest
      position identified from all points. None: ``coeffs`` are about the rig's rest
      position (a campaign file's coordinates).
    """

    parameter: float
    frequency: float
    stable: bool | None
    coeffs: np.ndarray
    forcing: np.ndarray | None
    noise: np.ndarray
    periods: float
    source: str
    stability_from: str = ""
    holding: Holding | None = None
    control: np.ndarray | None = None
    sensor_means: np.ndarray | None = None

    def __post_init__(self):
        c = _frozen(self.coeffs)
        if c.ndim != 2 or c.shape[1] != NCOEF:
            raise ValueError(f"{self.source}: coeffs must be (n_coord, {NCOEF}), got {c.shape}")
        object.__setattr__(self, "coeffs", c)
        if self.forcing is not None:
            fc = _frozen(self.forcing)
            if fc.shape != (NCOEF,):
                raise ValueError(f"{self.source}: forcing must be ({NCOEF},), got {fc.shape}")
            object.__setattr__(self, "forcing", fc)
        if self.sensor_means is not None:
            sm = _frozen(self.sensor_means)
            if sm.shape != (c.shape[0],):
                raise ValueError(f"{self.source}: sensor_means must be ({c.shape[0]},), got "
                                 f"{sm.shape}")
            object.__setattr__(self, "sensor_means", sm)
        if self.control is not None:
            uc = _frozen(self.control)
            if uc.shape != (NCOEF,):
                raise ValueError(f"{self.source}: control must be ({NCOEF},), got {uc.shape}")
            object.__setattr__(self, "control", uc)
        nz = _frozen(np.broadcast_to(np.asarray(self.noise, dtype=float), (c.shape[0],)))
        object.__setattr__(self, "noise", nz)
        object.__setattr__(self, "parameter", float(self.parameter))
        object.__setattr__(self, "frequency", float(self.frequency))
        object.__setattr__(self, "periods", float(self.periods))
        if self.stable is not None:
            object.__setattr__(self, "stable", bool(self.stable))

    @property
    def zero_known(self) -> bool:
        """Whether ``coeffs`` are about the rig's rest position."""
        return self.sensor_means is None

    @property
    def amplitude(self) -> float:
        """First-harmonic amplitude of coordinate 0 (heave / displacement), m."""
        return float(math.hypot(self.coeffs[0, 1], self.coeffs[0, 1 + K]))

    @property
    def omega(self) -> float:
        return 2.0 * math.pi * self.frequency


@dataclass(frozen=True, eq=False)
class OrbitDataset:
    """Periodic orbits of one system ("flutter" or "oscillator"), in load order.
    ``sensor_zero``: where the orbits' rest position came from when some file did not
    record it (:class:`~ude_fit.training.sensor_zero.SensorZero`), None otherwise."""

    system: str
    orbits: tuple[Orbit, ...]
    sources: tuple[str, ...]
    sensor_zero: object | None = None

    def __post_init__(self):
        system_kind(self.system)                      # a ValueError naming the known ones
        object.__setattr__(self, "orbits", tuple(self.orbits))
        object.__setattr__(self, "sources", tuple(str(s) for s in self.sources))
        n = len(COORDINATES[self.system])
        for o in self.orbits:
            if o.coeffs.shape[0] != n:
                raise ValueError(f"{o.source}: a {self.system} orbit has {n} coordinates, "
                                 f"this one {o.coeffs.shape[0]}")
            if (o.forcing is None) != self.kind.autonomous:
                raise ValueError(f"{o.source}: forcing must be given for oscillator orbits only")

    # ---- basics ---------------------------------------------------------------------------
    @property
    def kind(self) -> SystemKind:
        """What kind of system the orbits come from (autonomous aerofoil, forced oscillator)."""
        return KINDS[self.system]

    def __len__(self) -> int:
        return len(self.orbits)

    def __iter__(self):
        return iter(self.orbits)

    def __getitem__(self, i) -> Orbit:
        return self.orbits[i]

    @property
    def coordinates(self) -> tuple[str, ...]:
        return COORDINATES[self.system]

    @property
    def parameter_name(self) -> str:
        return PARAMETER_NAMES[self.system]

    def parameters(self) -> np.ndarray:
        return np.array([o.parameter for o in self.orbits], dtype=float)

    def frequencies(self) -> np.ndarray:
        return np.array([o.frequency for o in self.orbits], dtype=float)

    def known_stability(self) -> np.ndarray:
        """Mask of the orbits whose stability is known."""
        return np.array([o.stable is not None for o in self.orbits], dtype=bool)

    def stable(self) -> np.ndarray:
        """Stability labels as a bool array. Raises DataError if any orbit's is unknown:
        guessing False would silently turn unknown orbits into "unstable" ones; select
        the known ones first (ds.select(ds.known_stability()))."""
        for o in self.orbits:
            if o.stable is None:
                raise DataError(f"{o.source}: stability unknown (select known_stability() first)")
        return np.array([o.stable for o in self.orbits], dtype=bool)

    def unknown_stability(self) -> list[str]:
        """The sources of the points whose stability is unknown."""
        return [o.source for o in self.orbits if o.stable is None]

    def record(self) -> dict:
        """What every document of a command says of the points it read: how many, from
        where, and the sensors' zero they were taken about where their files do not record
        it (None where every file does)."""
        return {"points": len(self), "sources": list(self.sources),
                "sensor_zero": None if self.sensor_zero is None else self.sensor_zero.to_json()}

    def point_records(self) -> list[dict]:
        """Per point, what metrics.json records of its data: where it came from, its
        stability and that label's origin, and its holding control's figures."""
        return [{"source": o.source, "parameter": o.parameter, "frequency": o.frequency,
                 "stable": o.stable, "stability_from": o.stability_from or "unknown",
                 "holding": None if o.holding is None else o.holding.to_json()}
                for o in self.orbits]

    def amplitudes(self) -> np.ndarray:
        """First-harmonic amplitude sqrt(a1^2 + b1^2) of coordinate 0 (m)."""
        return np.array([o.amplitude for o in self.orbits], dtype=float)

    def coeffs(self) -> np.ndarray:
        """(n_orbits, n_coord, 15)."""
        n = len(self.coordinates)
        return (np.stack([o.coeffs for o in self.orbits]) if self.orbits
                else np.zeros((0, n, NCOEF)))

    def forcings(self) -> np.ndarray | None:
        """(n_orbits, 15) excitation coefficients (oscillator), None for flutter."""
        if self.kind.autonomous:
            return None
        return (np.stack([o.forcing for o in self.orbits]) if self.orbits
                else np.zeros((0, NCOEF)))

    def noise(self) -> np.ndarray:
        """(n_orbits, n_coord) residual RMS (NaN without a raw record)."""
        n = len(self.coordinates)
        return np.stack([o.noise for o in self.orbits]) if self.orbits else np.zeros((0, n))

    def select(self, mask) -> OrbitDataset:
        """The orbits picked by a boolean mask or an index array, same system and sources."""
        m = np.asarray(mask)
        if m.dtype == bool:
            if m.shape != (len(self),):
                raise ValueError(f"select: mask of shape {m.shape} for {len(self)} orbits")
            idx = np.flatnonzero(m)
        else:
            idx = m.astype(int).ravel()
        return OrbitDataset(self.system, tuple(self.orbits[i] for i in idx), self.sources,
                            self.sensor_zero)

    def zero_unknown(self) -> np.ndarray:
        """Mask of the orbits whose means are about a sensor zero no file recorded."""
        return np.array([not o.zero_known for o in self.orbits], dtype=bool)

    def frequencies_group(self) -> np.ndarray:
        """The distinct forcing frequencies (Hz, rounded to 1e-6 Hz), ascending (oscillator).

        Only the forced system's frequency is a setting that groups orbits into S-curves;
        an aerofoil's frequency is a measured output, so this raises for flutter."""
        if not self.kind.forced:
            raise DataError("frequencies_group: only for the forced oscillator (a flutter "
                            "orbit's frequency is an output, not a group)")
        return np.unique(np.round(self.frequencies(), 6))

    def parameter_spans(self) -> dict[str | None, tuple[float, float]]:
        """The measured parameter range of each branch family: {None: (lo, hi)} for
        self-excited data, {frequency key: (lo, hi)} per forcing frequency (the keys a
        forced diagram's folds have in the metrics, f"{Hz:g}")."""
        if not self.kind.forced:
            p = self.parameters()
            return {None: (float(p.min()), float(p.max()))}
        spans = {}
        for f in self.frequencies_group():
            p = self.at_frequency(f).parameters()
            spans[f"{float(f):g}"] = (float(p.min()), float(p.max()))
        return spans

    def at_frequency(self, freq: float) -> OrbitDataset:
        """The orbits whose frequency rounds (1e-6 Hz) to freq's."""
        return self.select(np.round(self.frequencies(), 6) == round(float(freq), 6))

    # ---- sampling -------------------------------------------------------------------------
    def sample(self, n: int = 64) -> dict:
        """Every orbit at the phases phi_j = 2 pi j / n, j = 0..n-1.

        Returns "phase" (n,), "q", "qdot", "qddot" (n_orbits, n, n_coord) and, for the
        oscillator, "forcing" (n_orbits, n). Time derivatives are exact derivatives of the
        series with t = phi / w, w = 2 pi f of each orbit (d/dt = w d/dphi).
        """
        n = int(n)
        if n < 1:
            raise ValueError("sample: n must be at least 1")
        phi = 2.0 * np.pi * np.arange(n) / n
        B = _basis(phi).T                                  # (n, 15)
        k = np.arange(1, K + 1, dtype=float)
        dB = np.zeros_like(B)                              # d/dphi of each basis function
        dB[:, 1:K + 1] = -k * B[:, K + 1:]
        dB[:, K + 1:] = k * B[:, 1:K + 1]
        ddB = np.zeros_like(B)
        ddB[:, 1:] = -np.concatenate([k, k]) ** 2 * B[:, 1:]
        C = self.coeffs()                                  # (m, c, 15)
        w = 2.0 * np.pi * self.frequencies()[:, None, None]
        out = {
            "phase": phi,
            "q": np.einsum("mcj,nj->mnc", C, B),
            "qdot": w * np.einsum("mcj,nj->mnc", C, dB),
            "qddot": w ** 2 * np.einsum("mcj,nj->mnc", C, ddB),
        }
        if self.kind.forced:
            out["forcing"] = self.forcings() @ B.T
        return out

    def __repr__(self) -> str:
        return (f"OrbitDataset(system={self.system!r}, {len(self)} orbits, "
                f"sources={list(self.sources)!r})")


# ==== frames ======================================================================================

def _flutter_frame(coeffs: np.ndarray, control: np.ndarray | None = None):
    """(coeffs, control) shifted so the heave's fundamental is +A cos(phi), the control
    (15,) by the same angle (None stays None)."""
    d = math.atan2(coeffs[0, 1 + K], coeffs[0, 1])
    return shift_phase(coeffs, d), None if control is None else shift_phase(control, d)


def _oscillator_frame(coeffs: np.ndarray, forcing: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shift both so the excitation's fundamental is +Phi cos(phi)."""
    d = math.atan2(forcing[1 + K], forcing[1])
    return shift_phase(coeffs, d), shift_phase(forcing, d)


