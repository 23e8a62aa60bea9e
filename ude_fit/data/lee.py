"""The lee2020 wind-tunnel files (MATLAB v5, one orbit per file) read into an
:class:`OrbitDataset`; the heave is converted from volts here and nowhere else."""

from __future__ import annotations

import math
import os

import numpy as np

from .._fourier import K, NCOEF, _fit, refine_frequency
from .holding import measure_holding
from .stability import stability_from_name
from .orbit import DataError, Orbit, OrbitDataset, _check_file, _flutter_frame, _one_line

LEE_HEAVE_M_PER_V = 0.18          # heave sensor sensitivity given with the data (m/V)
LEE_RATE_HZ = 5000.0              # the rig's loop rate, if a file has no usable `time`
LEE_PITCH_INVALID = 2 * math.pi - 1e-5   # pitch readings at/above this are encoder dropouts
_MAT5_HEADER = b"MATLAB 5.0 MAT-file"


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
    # The sensor's DC level (~3.3 V) and the encoder's zero are not the rig's rest
    # position, and neither is recorded: the orbit is kept about its own mean, and that
    # mean in the sensors' frame beside it (sensor_means), for the dataset's zero to be
    # identified from all points (training.sensor_zero) where the fit asks for it
    heave_level = heave.mean()
    heave = heave - heave_level                      # the sensor's ~3.3 V offset
    raw = data[3]
    # The pitch row is not wrapped in these files: its valid readings stay within
    # 0.26..0.46 rad, but 2-22 % of the samples, in bursts of ~15 at a few fixed angles,
    # read exactly 2 pi (1 - 2^-20) = 6.283179 rad, the 20-bit encoder's all-ones code: a
    # failed read. np.unwrap would turn each burst into a -0.35 rad spike (residual RMS as
    # large as the pitch amplitude), so those samples are left out of the pitch fit, and
    # only the valid ones are unwrapped (a no-op here). The encoder's absolute angle holds
    # the rig's zero, so the offset is removed as for the heave: the mean, here the fitted
    # one (below), since the failed reads cluster at a few angles of the cycle and the plain
    # mean of the samples left would be biased by where they fall (-5 mrad, a fifth of the
    # pitch amplitude, on the lee2020 points with 18-22 % of the reads failed).
    ok = np.isfinite(raw) & (raw < LEE_PITCH_INVALID)
    if ok.sum() < 8 * NCOEF:
        raise DataError(f"{path}: only {int(ok.sum())} valid pitch samples")
    pitch = np.zeros(n)
    pitch[ok] = np.unwrap(raw[ok])
    pitch_level = pitch[ok].mean()
    pitch[ok] -= pitch_level                       # (for conditioning; the fit's mean follows)
    if not np.all(np.isfinite(heave)):
        raise DataError(f"{path}: the heave row holds non-finite samples")
    freq = refine_frequency(t, heave, f0)
    phi = 2.0 * np.pi * freq * t
    valid = np.column_stack([np.ones(n, dtype=bool), ok])
    coeffs, noise = _fit(phi, np.column_stack([heave, pitch]), K, valid)
    # the fitted means in the sensors' frame (the encoder's angle in [0, 2 pi), as it reads)
    sensor_means = np.array([heave_level + coeffs[0, 0],
                             (pitch_level + coeffs[1, 0]) % (2 * np.pi)])
    coeffs[1, 0] = 0.0                             # the pitch's offset: its fitted mean
    # the control target (row 1) is in the heave sensor's volts, the control (row 2) in the
    # actuator's volts (its gain N/V is not in the files)
    holding = measure_holding(phi, data[0], data[1], data[2], "V")
    control = None
    if np.all(np.isfinite(data[2])):
        control = _fit(phi, data[2][:, None].astype(float), K)[0][0]
        # the heave's mean was removed (the sensor's offset), so the static force balance
        # it would close is unknown: the control's mean is left out with it
        control[0] = 0.0
    stable = stability_from_name(path)
    coeffs, control = _flutter_frame(coeffs, control)
    return Orbit(parameter=V, frequency=freq, stable=stable,
                 stability_from="" if stable is None else "file name",
                 coeffs=coeffs, forcing=None, noise=noise,
                 periods=n / rate * freq, source=path, holding=holding, control=control,
                 sensor_means=sensor_means)


def load_lee(path) -> OrbitDataset:
    """lee2020 model-2 CBC points: one .mat file, or a directory of them (all *.mat there,
    in name order). Heave row 0 (V -> m at 0.18 m/V, DC removed), pitch row 3 (unwrapped,
    mean removed), each mean kept in the sensors' frame (``sensor_means``); frequency from
    freq_actual, refined on the record; stability from the file name
    (:data:`~.stability.NAME_CONVENTIONS`; anything else unknown)."""
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


