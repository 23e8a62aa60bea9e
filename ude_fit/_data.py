"""The dataset of periodic orbits: campaign HDF5 files and the lee2020 wind-tunnel files.

Every orbit is kept as a truncated Fourier series over one period, K = 7 harmonics,
coefficients in the order a0, a1..a7, b1..b7 (15 numbers per coordinate):

    q(phi) = a0 + sum_k a_k cos(k phi) + b_k sin(k phi),    phi = 2 pi f t.

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
(0.18 m/V) and nothing else in this module sees volts.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Iterable
from dataclasses import dataclass

import h5py
import numpy as np
from scipy.optimize import minimize_scalar

__all__ = ["K", "NCOEF", "DataError", "Orbit", "OrbitDataset", "fourier_fit",
           "refine_frequency", "shift_phase", "evaluate", "load_campaign", "load_lee", "load"]

K = 7
NCOEF = 2 * K + 1
COORDINATES = {"flutter": ("h", "alpha"), "oscillator": ("x",)}
PARAMETER_NAMES = {"flutter": "airspeed", "oscillator": "forcing_amplitude"}

CAMPAIGN_FORMAT = "cbc-campaign"
CAMPAIGN_VERSION = 1
LEE_HEAVE_M_PER_V = 0.18          # heave sensor sensitivity given with the data (m/V)
LEE_RATE_HZ = 5000.0              # the rig's loop rate, if a file has no usable `time`
LEE_PITCH_INVALID = 2 * math.pi - 1e-5   # pitch readings at/above this are encoder dropouts
REFINE_REL = 0.02                 # refine_frequency searches freq0 * (1 +- 2 %)
MIN_PERIODS = 2.0                 # a raw record shorter than this is not used for the average

_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_MAT5_HEADER = b"MATLAB 5.0 MAT-file"
_MAT73_HEADER = b"MATLAB 7.3 MAT-file"
_JSON_ATTRS = "_json_attrs"
_RECORD_FIELDS = ("sample", "x", "q2", "phase", "control", "parameter")


class DataError(Exception):
    """Input that cannot become a dataset. The message is one line and names the file."""

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()))


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split()) or type(e).__name__


# ==== Fourier series ==============================================================================

def _basis(phi: np.ndarray, k_max: int = K) -> np.ndarray:
    """(2k_max + 1, N) rows [1, cos phi .. cos k phi, sin phi .. sin k phi].

    Row-major on purpose: every product the fits need (A A^T, Y^T A^T, c A) is then a
    plain contiguous matrix product, ~4x faster on 100k-sample records than with the
    (N, 15) design matrix.
    """
    phi = np.asarray(phi, dtype=float).ravel()
    A = np.empty((2 * k_max + 1, phi.size))
    A[0] = 1.0
    z1 = np.exp(1j * phi)
    z = z1.copy()
    for k in range(1, k_max + 1):
        A[k] = z.real
        A[k_max + k] = z.imag
        z *= z1                     # powers by recurrence: one complex exp instead of 2K trig calls
    return A


def evaluate(coeffs, phi) -> np.ndarray:
    """The series at phases phi; coeffs (..., 2K+1) gives (..., len(phi))."""
    c = np.asarray(coeffs, dtype=float)
    kk = (c.shape[-1] - 1) // 2
    return c @ _basis(np.atleast_1d(phi), kk)


def shift_phase(coeffs, delta: float) -> np.ndarray:
    """Coefficients of q(phi + delta): the same orbit with its phase origin moved by delta."""
    c = np.array(coeffs, dtype=float)
    kk = (c.shape[-1] - 1) // 2
    k = np.arange(1, kk + 1)
    cs, sn = np.cos(k * delta), np.sin(k * delta)
    a, b = c[..., 1:kk + 1].copy(), c[..., kk + 1:].copy()
    c[..., 1:kk + 1] = a * cs + b * sn
    c[..., kk + 1:] = b * cs - a * sn
    return c


def _fit(phi: np.ndarray, Y: np.ndarray, k_max: int = K,
         valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Least squares of the columns of Y (N, m) on the series in phi: ((m, 2k+1), rms (m,)).

    valid (N, m) bool, optional: samples each column may use (the others are ignored);
    the residual RMS is over the valid samples.
    """
    A = _basis(phi, k_max)
    YT = np.ascontiguousarray(np.asarray(Y, dtype=float).reshape(A.shape[1], -1).T)
    m = YT.shape[0]
    VT = None if valid is None else np.ascontiguousarray(np.asarray(valid, dtype=bool).T)
    G = A @ A.T
    rhs = (YT if VT is None else np.where(VT, YT, 0.0)) @ A.T        # (m, 2k+1)
    coef = np.empty((m, A.shape[0]))
    for j in range(m):
        Gj = G
        if VT is not None and not VT[j].all():
            Ax = A[:, ~VT[j]]
            Gj = G - Ax @ Ax.T                 # cheaper than re-forming it: few samples are out
        # Over whole periods the basis is nearly orthogonal (G ~ N/2 I), so the normal
        # equations are as accurate as an SVD and several times faster on 100k-sample
        # records; a record too short for that (ill-conditioned G) goes through the SVD.
        if np.linalg.cond(Gj) < 1e6:
            coef[j] = np.linalg.solve(Gj, rhs[j])
        else:
            v = slice(None) if VT is None else VT[j]
            coef[j] = np.linalg.lstsq(A[:, v].T, YT[j, v], rcond=None)[0]
    resid = YT - coef @ A
    if VT is None:
        rms = np.sqrt(np.einsum("ij,ij->i", resid, resid) / A.shape[1])
    else:
        resid[~VT] = 0.0
        rms = np.sqrt(np.einsum("ij,ij->i", resid, resid) / np.maximum(VT.sum(axis=1), 1))
    return coef, rms


def fourier_fit(t, y, freq: float, K: int = K):
    """Least-squares Fourier series (DC + K harmonics of `freq`, Hz) of a record y(t).

    The fit runs over the whole record, many periods, which is what averages the noise
    away. Returns (coeffs (2K+1,), residual RMS); y may also be (N, m), giving
    ((m, 2K+1), (m,)). Phase origin: t = t[0].
    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    if t.ndim != 1 or y.shape[0] != t.size:
        raise ValueError(f"fourier_fit: t has {t.size} samples, y has shape {y.shape}")
    if t.size < 2 * K + 2:
        raise ValueError(f"fourier_fit: {t.size} samples are too few for {2 * K + 1} coefficients")
    phi = 2.0 * np.pi * freq * (t - t[0])
    coef, rms = _fit(phi, y.reshape(t.size, -1), K)
    if y.ndim == 1:
        return coef[0], float(rms[0])
    return coef, rms


def refine_frequency(t, y, freq0: float, rel: float = REFINE_REL, harmonics: int = 3) -> float:
    """The frequency within freq0 * (1 +- rel) at which a periodic series (DC + the first
    `harmonics` harmonics) fits the record y(t) best: least squares, i.e. the maximum-
    likelihood estimate in white noise. The fundamental carries nearly all of the
    information; the next harmonics are fitted too because, left out, they bias a short
    record's estimate (~1e-3 relative over 5 periods of a signal with 5-10 % harmonics).

    A logged frequency a fraction of a per cent off smears a many-period average (the
    phase slips by 2 pi * error * periods over the record), so it is re-measured here.
    A grid finer than the spectral line width finds the right peak even where the
    bracket holds side lobes (long records); a bounded scalar search then polishes it.
    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    if t.ndim != 1 or t.size != y.size or t.size < 8 or not freq0 > 0:
        raise ValueError("refine_frequency: need matching 1-D t, y (at least 8 samples) "
                         "and freq0 > 0")
    t = t - t[0]
    y = y - y.mean()
    # the objective is narrow-band, so a 5 kHz record is decimated to ~128 samples a period
    # to keep the search cheap (the estimate's scatter grows only as sqrt(step))
    per_period = t.size / max(t[-1] * freq0, 1e-12)
    step = max(1, int(per_period // 128))
    td, yd = t[::step], y[::step]
    h = max(1, int(harmonics))

    def unexplained(f: float) -> float:
        A = _basis(2.0 * np.pi * f * td, h)
        r = A @ yd
        try:
            c = np.linalg.solve(A @ A.T, r)
        except np.linalg.LinAlgError:
            c = np.linalg.lstsq(A.T, yd, rcond=None)[0]
        return float(yd @ yd - r @ c)

    lo, hi = freq0 * (1.0 - rel), freq0 * (1.0 + rel)
    span = max(t[-1], 1e-12)
    n_grid = int(min(max(np.ceil((hi - lo) * span * 8.0), 8), 4000)) + 1
    grid = np.linspace(lo, hi, n_grid)
    vals = np.array([unexplained(f) for f in grid])
    i = int(np.argmin(vals))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, n_grid - 1)]
    res = minimize_scalar(unexplained, bounds=(a, b), method="bounded",
                          options={"xatol": 1e-8 * freq0, "maxiter": 100})
    return float(res.x) if res.fun <= vals[i] else float(grid[i])


# ==== the dataset =================================================================================

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
    """

    parameter: float
    frequency: float
    stable: bool | None
    coeffs: np.ndarray
    forcing: np.ndarray | None
    noise: np.ndarray
    periods: float
    source: str

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
        nz = _frozen(np.broadcast_to(np.asarray(self.noise, dtype=float), (c.shape[0],)))
        object.__setattr__(self, "noise", nz)
        object.__setattr__(self, "parameter", float(self.parameter))
        object.__setattr__(self, "frequency", float(self.frequency))
        object.__setattr__(self, "periods", float(self.periods))
        if self.stable is not None:
            object.__setattr__(self, "stable", bool(self.stable))

    @property
    def amplitude(self) -> float:
        """First-harmonic amplitude of coordinate 0 (heave / displacement), m."""
        return float(math.hypot(self.coeffs[0, 1], self.coeffs[0, 1 + K]))

    @property
    def omega(self) -> float:
        return 2.0 * math.pi * self.frequency


@dataclass(frozen=True, eq=False)
class OrbitDataset:
    """Periodic orbits of one system ("flutter" or "oscillator"), in load order."""

    system: str
    orbits: tuple[Orbit, ...]
    sources: tuple[str, ...]

    def __post_init__(self):
        if self.system not in COORDINATES:
            raise ValueError(f"system must be 'flutter' or 'oscillator', not {self.system!r}")
        object.__setattr__(self, "orbits", tuple(self.orbits))
        object.__setattr__(self, "sources", tuple(str(s) for s in self.sources))
        n = len(COORDINATES[self.system])
        for o in self.orbits:
            if o.coeffs.shape[0] != n:
                raise ValueError(f"{o.source}: a {self.system} orbit has {n} coordinates, "
                                 f"this one {o.coeffs.shape[0]}")
            if (o.forcing is None) != (self.system == "flutter"):
                raise ValueError(f"{o.source}: forcing must be given for oscillator orbits only")

    # ---- basics ---------------------------------------------------------------------------
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
        if self.system == "flutter":
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
        return OrbitDataset(self.system, tuple(self.orbits[i] for i in idx), self.sources)

    def frequencies_group(self) -> np.ndarray:
        """The distinct forcing frequencies (Hz, rounded to 1e-6 Hz), ascending (oscillator).

        Only the forced system's frequency is a setting that groups orbits into S-curves;
        an aerofoil's frequency is a measured output, so this raises for flutter."""
        if self.system != "oscillator":
            raise DataError("frequencies_group: only for the forced oscillator (a flutter "
                            "orbit's frequency is an output, not a group)")
        return np.unique(np.round(self.frequencies(), 6))

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
        if self.system == "oscillator":
            out["forcing"] = self.forcings() @ B.T
        return out

    def __repr__(self) -> str:
        return (f"OrbitDataset(system={self.system!r}, {len(self)} orbits, "
                f"sources={list(self.sources)!r})")


# ==== frames ======================================================================================

def _flutter_frame(coeffs: np.ndarray) -> np.ndarray:
    """Shift so the heave's fundamental is +A cos(phi)."""
    return shift_phase(coeffs, math.atan2(coeffs[0, 1 + K], coeffs[0, 1]))


def _oscillator_frame(coeffs: np.ndarray, forcing: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shift both so the excitation's fundamental is +Phi cos(phi)."""
    d = math.atan2(forcing[1 + K], forcing[1])
    return shift_phase(coeffs, d), shift_phase(forcing, d)


# ==== campaign files ==============================================================================

def _py(v):
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    if isinstance(v, np.generic):
        return v.item()
    return v


def _attrs(obj) -> dict:
    """An HDF5 object's attributes as Python values, JSON-encoded ones decoded (see
    docs/hdf5_layout.md: names listed in `_json_attrs`)."""
    raw = obj.attrs
    as_json = set()
    if _JSON_ATTRS in raw:
        try:
            as_json = set(json.loads(_py(raw[_JSON_ATTRS])))
        except (TypeError, ValueError):
            as_json = set()
    out = {}
    for k in raw:
        if k == _JSON_ATTRS:
            continue
        try:
            v = _py(raw[k])
        except (OSError, TypeError, ValueError):
            continue                   # an attribute h5py cannot decode is not one we need
        if k in as_json and isinstance(v, str):
            try:
                v = json.loads(v)
            except ValueError:
                pass
        out[k] = v
    return out


def _signature_offset(path: str) -> int | None:
    """Offset of the HDF5 signature (0, 512, 1024, ...: a user block may precede it)."""
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        off = 0
        while off + 8 <= size:
            fh.seek(off)
            if fh.read(8) == _HDF5_SIGNATURE:
                return off
            off = 512 if off == 0 else off * 2
    return None


def _as_float(v, default=float("nan")) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return default
    return f


def _dataset(g, path: str):
    d = g.get(path)
    return None if d is None or not isinstance(d, h5py.Dataset) else d[()]


def _coeff_array(v, what: str) -> np.ndarray:
    a = np.asarray(v, dtype=float).ravel()
    if a.shape != (NCOEF,) or not np.all(np.isfinite(a)):
        raise DataError(f"{what}: expected {NCOEF} finite Fourier coefficients, got shape "
                        f"{np.shape(v)}")
    return a


def _record(g) -> dict | None:
    """The point's raw record as 1-D float arrays of one length, or None if it has none."""
    ts = g.get("timeseries")
    if ts is None or not isinstance(ts, h5py.Group) or len(ts) == 0:
        return None
    out = {}
    for name in _RECORD_FIELDS:               # the others (x_dot, target, ...) are not needed
        d = ts.get(name)
        if isinstance(d, h5py.Dataset) and d.ndim == 1 and d.dtype.kind in "biuf":
            out[name] = d[()]
    lengths = {v.size for v in out.values()}
    if not out or len(lengths) != 1 or lengths.pop() == 0:
        return None
    return out


def _flutter_point(g, label: str, rec: dict | None, sample_rate: float, a: dict,
                   settings: dict) -> Orbit:
    freq = _as_float(a.get("frequency"))
    if not freq > 0:
        raise DataError(f"{label}: no valid frequency ({a.get('frequency')!r})")
    noise = np.full(2, np.nan)
    periods = _as_float(settings.get("navg"))
    coeffs = None
    if (rec is not None and sample_rate > 0 and "sample" in rec and "x" in rec and "q2" in rec):
        t = rec["sample"].astype(float) / sample_rate
        dur = float(t[-1] - t[0]) if t.size > 1 else 0.0
        Y = np.column_stack([rec["x"], rec["q2"]]).astype(float)
        if dur * freq >= MIN_PERIODS and t.size >= 8 * NCOEF and np.all(np.isfinite(Y)):
            freq = refine_frequency(t, Y[:, 0], freq)
            coeffs, noise = fourier_fit(t, Y, freq)
            periods = dur * freq
    if coeffs is None:
        resp = _dataset(g, "fourier/response/mean")
        second = _dataset(g, "fourier/second/mean")
        if resp is None or second is None:
            raise DataError(f"{label}: no raw record and no fourier/response and "
                            "fourier/second means")
        coeffs = np.stack([_coeff_array(resp, f"{label}: fourier/response/mean"),
                           _coeff_array(second, f"{label}: fourier/second/mean")])
    airspeed = _as_float(a.get("parameter"))
    if not math.isfinite(airspeed):
        raise DataError(f"{label}: no valid airspeed (parameter = {a.get('parameter')!r})")
    return Orbit(parameter=airspeed, frequency=freq,
                 stable=_stable_attr(a), coeffs=_flutter_frame(coeffs), forcing=None,
                 noise=noise, periods=periods, source=label)


def _oscillator_point(g, label: str, rec: dict | None, sample_rate: float, a: dict,
                      settings: dict) -> Orbit:
    freq = _as_float(a.get("frequency"))
    if not freq > 0:
        freq = _as_float(settings.get("frequency"))
    if not freq > 0:
        raise DataError(f"{label}: no valid forcing frequency")
    noise = np.full(1, np.nan)
    periods = _as_float(settings.get("navg"))
    coeffs = forcing = None
    if rec is not None and "x" in rec and "phase" in rec and "control" in rec:
        # The ring's `phase` is the board's forcing phase itself, so fitting against it puts
        # response and excitation in the board's frame without any timing assumptions (and
        # without the ~0.1 % leak of the board's running correlation when a period is not a
        # whole number of samples, which the campaign's own record fit avoids the same way).
        th = rec["phase"].astype(float)
        x = rec["x"].astype(float)
        u = rec["control"].astype(float)
        span = float(np.ptp(np.unwrap(th))) / (2.0 * np.pi) if th.size > 1 else 0.0
        if span >= MIN_PERIODS and th.size >= 8 * NCOEF and np.all(np.isfinite(x)):
            # total excitation = host forcing Phi_host cos(th) + control (kernel.py); the
            # setting is exact where the ring's parameter field is quantised to 16 bits
            host = _as_float(settings.get("forcing_amplitude"))
            if not math.isfinite(host):
                host = float(np.median(rec["parameter"])) if "parameter" in rec else 0.0
            exc = u + host * np.cos(th)
            coef, rms = _fit(th, np.column_stack([x, exc]))
            coeffs, forcing = coef[:1], coef[1]
            noise = rms[:1]
            periods = span
    if coeffs is None:
        resp = _dataset(g, "fourier/response/mean")
        exc = _dataset(g, "fourier/excitation/mean")
        if resp is None or exc is None:
            raise DataError(f"{label}: no raw record and no fourier/response and "
                            "fourier/excitation means")
        coeffs = _coeff_array(resp, f"{label}: fourier/response/mean")[None, :]
        forcing = _coeff_array(exc, f"{label}: fourier/excitation/mean")
        if rec is not None and "x" in rec and rec["x"].size >= 8 * NCOEF:
            # no phase field: the record can still say how noisy the point is, fitted in
            # time at the (fixed, known) forcing frequency
            if "sample" in rec and sample_rate > 0:
                t = rec["sample"].astype(float) / sample_rate
                if float(t[-1] - t[0]) * freq >= MIN_PERIODS:
                    noise = np.array([fourier_fit(t, rec["x"].astype(float), freq)[1]])
    if not math.hypot(forcing[1], forcing[1 + K]) > 0:
        raise DataError(f"{label}: the excitation has no fundamental, so no forcing frame")
    coeffs, forcing = _oscillator_frame(coeffs, forcing)
    param = _as_float(a.get("parameter"))
    if not math.isfinite(param):
        param = math.hypot(forcing[1], forcing[1 + K])
    return Orbit(parameter=param, frequency=freq, stable=_stable_attr(a), coeffs=coeffs,
                 forcing=forcing, noise=noise, periods=periods, source=label)


def _stable_attr(a: dict) -> bool | None:
    v = a.get("stable")
    if v is None or isinstance(v, str):
        return None
    return bool(v)


def _system_of(f: h5py.File, path: str) -> str:
    rig = _py(f.attrs.get("rig", "unknown"))
    if rig in COORDINATES:
        return rig
    ident = f.get("metadata/identity")
    if ident is not None:
        kind = _attrs(ident).get("rig_kind")
        if kind in (0, 1):
            return "flutter" if kind == 0 else "oscillator"
    for g in f.get("points", {}).values():
        r = _py(g.attrs.get("rig", ""))
        if r in COORDINATES:
            return r
    raise DataError(f"{path}: campaign file of unknown rig (root attribute rig={rig!r})")


def load_campaign(path) -> OrbitDataset:
    """The complete, converged points (complete == True, status == "ok") of a campaign
    file (docs/hdf5_layout.md), read with plain h5py.

    Per point, with a raw record: flutter h and alpha are fitted over the whole record at
    the frequency refined from it (the logged one as the starting guess); the oscillator's
    response and total excitation are fitted against the recorded forcing phase. Without a
    record, the board's averaged coefficients (fourier/<channel>/mean) are used and noise
    is NaN. The result may be empty (a campaign still starting); `load` refuses that.
    """
    path = os.fspath(path)
    _check_file(path)
    if _signature_offset(path) is None:
        raise DataError(f"{path}: not a campaign file (not an HDF5 file)")
    if os.path.exists(path + "-journal"):
        raise DataError(f"{path}: has a hot journal ({os.path.basename(path)}-journal): the "
                        "campaign is being written or was killed mid-commit; resume it (or read "
                        "it with cbc_controller.log.read_campaign) and load it again")
    try:
        with h5py.File(path, "r", locking=False) as f:
            return _read_campaign(f, path)
    except DataError:
        raise
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as e:
        raise DataError(f"{path}: cannot be read as a campaign file ({_one_line(e)})") from None


def _read_campaign(f: h5py.File, path: str) -> OrbitDataset:
    fmt = _py(f.attrs.get("format", None))
    if fmt != CAMPAIGN_FORMAT:
        raise DataError(f"{path}: not a campaign file (an HDF5 file without "
                        f"format={CAMPAIGN_FORMAT!r} in its root attributes)")
    version = _as_float(_py(f.attrs.get("format_version", None)))
    if not math.isfinite(version):
        raise DataError(f"{path}: campaign file without a format_version")
    if version > CAMPAIGN_VERSION:
        raise DataError(f"{path}: campaign format version {int(version)} is newer than this "
                        f"reader's ({CAMPAIGN_VERSION}); update ude_fit")
    system = _system_of(f, path)
    ident = f.get("metadata/identity")
    sample_rate = _as_float(_attrs(ident).get("sample_rate")) if ident is not None else math.nan
    points = f.get("points")
    orbits = []
    if points is not None:
        for name in sorted(points):
            g = points[name]
            if not isinstance(g, h5py.Group):
                continue
            a = _attrs(g)
            if a.get("complete") is not True or a.get("status") != "ok":
                continue
            label = f"{path}#{a.get('key', 'points/' + name)}"
            settings = _attrs(g["settings"]) if isinstance(g.get("settings"), h5py.Group) else {}
            rec = _record(g)
            if system == "flutter":
                if rec is not None and not sample_rate > 0:
                    raise DataError(f"{path}: raw records but no sample_rate in "
                                    "/metadata/identity")
                orbits.append(_flutter_point(g, label, rec, sample_rate, a, settings))
            else:
                orbits.append(_oscillator_point(g, label, rec, sample_rate, a, settings))
    return OrbitDataset(system, tuple(orbits), (path,))


# ==== lee2020 wind-tunnel files ===================================================================

_LEE_STABLE = re.compile(r"^CBC_stable_", re.IGNORECASE)
_LEE_UNSTABLE = re.compile(r"^CBC_v", re.IGNORECASE)


def _lee_stability(name: str) -> bool | None:
    if _LEE_STABLE.match(name):
        return True
    if _LEE_UNSTABLE.match(name):
        return False
    return None


def _scalar(m: dict, key: str, path: str) -> float:
    if key not in m:
        raise DataError(f"{path}: not a lee2020 CBC point file (no variable {key!r})")
    v = np.asarray(m[key], dtype=float).ravel()
    if v.size != 1 or not np.isfinite(v[0]):
        raise DataError(f"{path}: {key} is not one finite number")
    return float(v[0])


def _lee_file(path: str) -> Orbit:
    from scipy.io import loadmat          # scipy.io pulls in a lot; only the lee path needs it
    try:
        m = loadmat(path, variable_names=["data", "time", "Wind_sped", "freq_actual"])
    except Exception as e:               # loadmat raises many types for a bad file
        raise DataError(f"{path}: not a readable .mat file ({_one_line(e)})") from None
    if "data" not in m:
        raise DataError(f"{path}: not a lee2020 CBC point file (no variable 'data')")
    data = np.asarray(m["data"], dtype=float)
    if data.ndim != 2 or data.shape[0] < 4 or data.shape[1] < 8 * NCOEF:
        raise DataError(f"{path}: data has shape {data.shape}; expected 5 rows of samples")
    V = _scalar(m, "Wind_sped", path)
    f0 = _scalar(m, "freq_actual", path)
    if not f0 > 0:
        raise DataError(f"{path}: freq_actual = {f0} is not a frequency")
    n = data.shape[1]
    # Two files hold 10,000 samples but the full 100,000-entry `time`: only the spacing is
    # trusted (the phase origin is re-chosen anyway), and it must be uniform.
    t_file = np.asarray(m.get("time", np.zeros(0)), dtype=float).ravel()
    rate = LEE_RATE_HZ
    if t_file.size >= 2:
        d = np.diff(t_file[:min(t_file.size, n)])
        if d.size and np.all(d > 0) and np.ptp(d) <= 1e-6 * np.median(d):
            rate = 1.0 / float(np.median(d))
    t = np.arange(n) / rate
    heave = data[0] * LEE_HEAVE_M_PER_V              # volts -> metres, at the edge
    heave = heave - heave.mean()                     # the sensor's ~3.3 V offset
    raw = data[3]
    # The pitch row is not wrapped in these files: its valid readings stay within
    # 0.26..0.46 rad, but 2-22 % of the samples, in bursts of ~15 at a few fixed angles,
    # read exactly 2 pi (1 - 2^-20) = 6.283179 rad, the 20-bit encoder's all-ones code: a
    # failed read. np.unwrap would turn each burst into a -0.35 rad spike (residual RMS as
    # large as the pitch amplitude), so those samples are left out of the pitch fit, and
    # only the valid ones are unwrapped (a no-op here) and offset-corrected.
    ok = np.isfinite(raw) & (raw < LEE_PITCH_INVALID)
    if ok.sum() < 8 * NCOEF:
        raise DataError(f"{path}: only {int(ok.sum())} valid pitch samples")
    pitch = np.zeros(n)
    pitch[ok] = np.unwrap(raw[ok])
    pitch[ok] -= pitch[ok].mean()
    if not np.all(np.isfinite(heave)):
        raise DataError(f"{path}: the heave row holds non-finite samples")
    freq = refine_frequency(t, heave, f0)
    phi = 2.0 * np.pi * freq * t
    valid = np.column_stack([np.ones(n, dtype=bool), ok])
    coeffs, noise = _fit(phi, np.column_stack([heave, pitch]), K, valid)
    return Orbit(parameter=V, frequency=freq, stable=_lee_stability(os.path.basename(path)),
                 coeffs=_flutter_frame(coeffs), forcing=None, noise=noise,
                 periods=n / rate * freq, source=path)


def load_lee(path) -> OrbitDataset:
    """lee2020 model-2 CBC points: one .mat file, or a directory of them (all *.mat there,
    in name order). Heave row 0 (V -> m at 0.18 m/V, DC removed), pitch row 3 (unwrapped,
    mean removed); frequency from freq_actual, refined on the record; stability from the
    file name (CBC_stable_* stable, CBC_v* unstable, anything else unknown)."""
    path = os.fspath(path)
    _check_file(path, allow_dir=True)
    if os.path.isdir(path):
        files = sorted(os.path.join(path, n) for n in os.listdir(path)
                       if n.lower().endswith(".mat") and os.path.isfile(os.path.join(path, n)))
        if not files:
            raise DataError(f"{path}: a directory without .mat files (give lee2020 .mat files "
                            "or a directory of them)")
    else:
        files = [path]
    orbits = tuple(_lee_file(p) for p in files)
    return OrbitDataset("flutter", orbits, (path,))


# ==== dispatch ====================================================================================

def _check_file(path: str, allow_dir: bool = False) -> None:
    if not os.path.exists(path):
        raise DataError(f"{path}: no such file or directory")
    if os.path.isdir(path) and not allow_dir:
        raise DataError(f"{path}: is a directory, not a file")
    if not os.access(path, os.R_OK):
        raise DataError(f"{path}: not readable (permission denied)")


def _kind(path: str) -> str:
    """'campaign', 'lee' or raises: decided by content, not by the file name."""
    _check_file(path, allow_dir=True)
    if os.path.isdir(path):
        return "lee"
    try:
        with open(path, "rb") as fh:
            head = fh.read(128)
        off = _signature_offset(path)
    except OSError as e:
        raise DataError(f"{path}: cannot be read ({_one_line(e)})") from None
    if head.startswith(_MAT73_HEADER):
        raise DataError(f"{path}: a MATLAB v7.3 file; lee2020 files are MATLAB v5 (save with "
                        "-v7)")
    if off is not None:
        return "campaign"
    if head.startswith(_MAT5_HEADER):
        return "lee"
    raise DataError(f"{path}: neither a campaign HDF5 file nor a lee2020 .mat file")


def load(paths, system: str | None = None) -> OrbitDataset:
    """One dataset from campaign files, lee2020 .mat files and directories of them.

    All inputs must be of one system (and of `system`, when given); the dataset must not
    be empty. Every problem is a DataError with a one-line message naming the file.
    """
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    paths = [os.fspath(p) for p in paths] if isinstance(paths, Iterable) else []
    if not paths:
        raise DataError("no input files given")
    if system is not None and system not in COORDINATES:
        raise DataError(f"unknown system {system!r} (flutter or oscillator)")
    parts = []
    for p in paths:
        ds = load_campaign(p) if _kind(p) == "campaign" else load_lee(p)
        if system is not None and ds.system != system:
            raise DataError(f"{p}: holds {ds.system} data, but {system} was asked for")
        if parts and ds.system != parts[0].system:
            raise DataError(f"{p}: holds {ds.system} data, but {parts[0].sources[0]} holds "
                            f"{parts[0].system} data; load one system at a time")
        parts.append(ds)
    orbits = tuple(o for ds in parts for o in ds.orbits)
    if not orbits:
        raise DataError(f"{', '.join(paths)}: no complete points (no point with complete=True "
                        "and status 'ok')")
    return OrbitDataset(parts[0].system, orbits, tuple(s for ds in parts for s in ds.sources))
