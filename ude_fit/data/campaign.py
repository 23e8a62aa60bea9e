"""Campaign HDF5 files (docs/hdf5_layout.md) read into an :class:`OrbitDataset`."""

from __future__ import annotations

import json
import math
import os

import h5py
import numpy as np

from .._fourier import K, NCOEF, _fit, fourier_fit, refine_frequency
from .._systems import KINDS
from .holding import measure_holding
from .stability import stability_from_name
from .orbit import (COORDINATES, DataError, Orbit, OrbitDataset, _check_file, _flutter_frame,
                    _one_line, _oscillator_frame)

CAMPAIGN_FORMAT = "cbc-campaign"
CAMPAIGN_VERSION = 1
MIN_PERIODS = 2.0                 # a raw record shorter than this is not used for the average

_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_JSON_ATTRS = "_json_attrs"
_RECORD_FIELDS = ("sample", "x", "q2", "phase", "control", "target", "parameter")


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
    return _contiguous_part(out)


def _contiguous_part(rec: dict) -> dict:
    """The longest stretch of the record whose sample counter steps by the ring's own step
    (one record every `ring_decimation` samples: the commonest step). Seen when a busy
    machine resumed a campaign: the rig overwrote ring records while the controller read
    them (the controller now drops such records), their 16-bit sample numbers were a lap
    ahead, and the unwrapped counter jumped forward (by 4097 and 61441) and back. The
    samples around such jumps are not dated by the counter; fitting the whole record by it
    put one point's amplitude 22 % below its own board means. A stretch too short to fit
    leaves the point to those means (``_flutter_point``)."""
    sample = rec.get("sample")
    if sample is None or sample.size < 2:
        return rec
    step = np.diff(sample)
    values, counts = np.unique(step, return_counts=True)
    breaks = np.flatnonzero(step != values[np.argmax(counts)]) + 1
    if breaks.size == 0:
        return rec
    edges = np.concatenate([[0], breaks, [sample.size]])
    k = int(np.argmax(np.diff(edges)))
    return {name: v[edges[k]:edges[k + 1]] for name, v in rec.items()}


def _flutter_point(g, label: str, rec: dict | None, sample_rate: float, a: dict,
                   settings: dict) -> Orbit:
    freq = _as_float(a.get("frequency"))
    if not freq > 0:
        raise DataError(f"{label}: no valid frequency ({a.get('frequency')!r})")
    noise = np.full(2, np.nan)
    periods = _as_float(settings.get("navg"))
    coeffs = holding = control = None
    if (rec is not None and sample_rate > 0 and "sample" in rec and "x" in rec and "q2" in rec):
        t = rec["sample"].astype(float) / sample_rate
        dur = float(t[-1] - t[0]) if t.size > 1 else 0.0
        Y = np.column_stack([rec["x"], rec["q2"]]).astype(float)
        if dur * freq >= MIN_PERIODS and t.size >= 8 * NCOEF and np.all(np.isfinite(Y)):
            freq = refine_frequency(t, Y[:, 0], freq)
            coeffs, noise = fourier_fit(t, Y, freq)
            periods = dur * freq
            holding = _holding(rec, 2.0 * np.pi * freq * t, settings, freq, "N")
            u = rec.get("control")
            if u is not None and np.all(np.isfinite(u)):
                control = fourier_fit(t, u.astype(float), freq)[0]   # same time origin
    if coeffs is None:
        resp = _dataset(g, "fourier/response/mean")
        second = _dataset(g, "fourier/second/mean")
        if resp is None or second is None:
            raise DataError(f"{label}: no raw record and no fourier/response and "
                            "fourier/second means")
        coeffs = np.stack([_coeff_array(resp, f"{label}: fourier/response/mean"),
                           _coeff_array(second, f"{label}: fourier/second/mean")])
        # the board correlates every channel against the same phase
        ctrl = _dataset(g, "fourier/control/mean")
        control = None if ctrl is None else _coeff_array(ctrl, f"{label}: fourier/control/mean")
    airspeed = _as_float(a.get("parameter"))
    if not math.isfinite(airspeed):
        raise DataError(f"{label}: no valid airspeed (parameter = {a.get('parameter')!r})")
    coeffs, control = _flutter_frame(coeffs, control)
    return Orbit(parameter=airspeed, frequency=freq,
                 **_stability(a, label), coeffs=coeffs, forcing=None,
                 noise=noise, periods=periods, source=label, holding=holding,
                 control=control)


def _oscillator_point(g, label: str, rec: dict | None, sample_rate: float, a: dict,
                      settings: dict) -> Orbit:
    freq = _as_float(a.get("frequency"))
    if not freq > 0:
        freq = _as_float(settings.get("frequency"))
    if not freq > 0:
        raise DataError(f"{label}: no valid forcing frequency")
    noise = np.full(1, np.nan)
    periods = _as_float(settings.get("navg"))
    coeffs = forcing = holding = None
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
            holding = _holding(rec, th, settings, freq, "m/s^2")
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
    return Orbit(parameter=param, frequency=freq, **_stability(a, label), coeffs=coeffs,
                 forcing=forcing, noise=noise, periods=periods, source=label,
                 holding=holding)


def _holding(rec: dict, phi, settings: dict, freq: float, unit: str):
    """The point's holding control (data.holding) from its raw record, None without the
    control and target fields; the controller's gains kp, kd from the point's settings."""
    if "control" not in rec or "target" not in rec:
        return None
    gains = (_as_float(settings.get("kp")), _as_float(settings.get("kd")))
    return measure_holding(phi, rec["x"].astype(float), rec["target"].astype(float),
                           rec["control"].astype(float), unit,
                           gains=gains if all(map(math.isfinite, gains)) else None,
                           omega=2.0 * math.pi * freq)


def _stable_attr(a: dict) -> bool | None:
    v = a.get("stable")
    if v is None or isinstance(v, str):
        return None
    return bool(v)


def _stability(a: dict, label: str) -> dict:
    """The point's stability and where it came from: its ``stable`` attribute, else the
    lab's naming convention applied to its key, else unknown."""
    v = _stable_attr(a)
    if v is not None:
        return {"stable": v, "stability_from": "campaign attribute"}
    v = stability_from_name(label.partition("#")[2].rsplit("/", 1)[-1])
    return {"stable": v, "stability_from": "" if v is None else "point name"}


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
            if KINDS[system].autonomous:
                if rec is not None and not sample_rate > 0:
                    raise DataError(f"{path}: raw records but no sample_rate in "
                                    "/metadata/identity")
                orbits.append(_flutter_point(g, label, rec, sample_rate, a, settings))
            else:
                orbits.append(_oscillator_point(g, label, rec, sample_rate, a, settings))
    return OrbitDataset(system, tuple(orbits), (path,))


