"""The campaign file is the one contract between the controller and the fitting package, which
import nothing of each other: a file written by `cbc_controller`'s writer, read back by
`ude_fit`'s reader, gives the orbits the documents described (which points count, airspeed,
stability, frequency, and the heave and pitch harmonics, from the raw record or, without one,
from the board's averaged coefficients)."""

from __future__ import annotations

import numpy as np

from tests.test_campaign_log import point_doc, write_campaign
from ude_fit import load_campaign
from ude_fit._fourier import K

SAMPLE_RATE = 5000.0          # start_doc's identity block
FREQ = 5.0                    # 3000 samples (point_doc's record length) hold 3 periods


def _record(i: int, heave: float, pitch: float, n: int = 3000) -> dict:
    """A raw record of known harmonics: heave A cos + A/10 cos 3, pitch lagging by 0.7 rad."""
    sample = np.arange(n, dtype=np.int64) + 10_000 * i
    ph = 2 * np.pi * FREQ * sample / SAMPLE_RATE
    doc = point_doc(i, frequency=FREQ)["timeseries"]
    doc.update(sample=sample, x=heave * np.cos(ph) + 0.1 * heave * np.cos(3 * ph),
               q2=pitch * np.cos(ph - 0.7))
    return doc


def test_controller_file_read_by_the_fitting_package(tmp_path):
    path = tmp_path / "campaign.h5"
    stable = point_doc(0, frequency=FREQ, stable=True, parameter=18.0)
    stable["timeseries"] = _record(0, heave=0.02, pitch=0.1)
    unstable = point_doc(1, frequency=FREQ, stable=False, parameter=19.0)
    unstable["timeseries"] = _record(1, heave=0.01, pitch=0.04)
    failed = point_doc(2, status="not_converged", parameter=20.0)
    averaged = point_doc(3, frequency=FREQ, stable=False, parameter=21.0, timeseries=False)
    write_campaign(path, [stable, unstable, failed, averaged])

    ds = load_campaign(path)
    assert [o.parameter for o in ds.orbits] == [18.0, 19.0, 21.0]     # the failed point left out
    assert [o.stable for o in ds.orbits] == [True, False, False]
    for orbit, heave, pitch in zip(ds.orbits[:2], (0.02, 0.01), (0.1, 0.04)):
        c = np.asarray(orbit.coeffs)                                  # (2, 15): heave, pitch
        assert abs(orbit.frequency - FREQ) < 1e-6 * FREQ
        # the heave's fundamental is +A cos(phi) in the fitting package's frame
        np.testing.assert_allclose([c[0, 1], c[0, 1 + K]], [heave, 0.0], atol=1e-9)
        np.testing.assert_allclose(np.hypot(c[0, 3], c[0, 3 + K]), 0.1 * heave, rtol=1e-6)
        np.testing.assert_allclose(np.hypot(c[1, 1], c[1, 1 + K]), pitch, rtol=1e-6)
        # pitch lags heave by 0.7 rad
        np.testing.assert_allclose(np.arctan2(c[1, 1 + K], c[1, 1]), 0.7, atol=1e-6)
    # no raw record: the board's averaged coefficients, turned into the same frame
    resp = averaged["fourier"]["response"]["mean"]
    c = np.asarray(ds.orbits[2].coeffs)
    np.testing.assert_allclose(c[0, 1], np.hypot(resp[1], resp[1 + K]), rtol=1e-12)
    np.testing.assert_allclose(np.hypot(c[1, 1], c[1, 1 + K]),
                               np.hypot(*averaged["fourier"]["second"]["mean"][[1, 1 + K]]),
                               rtol=1e-12)
