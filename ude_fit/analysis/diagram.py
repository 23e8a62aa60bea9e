"""A model's bifurcation diagram: the windows it is traced over (from the data's extent),
the tracing (the branch from the Hopf point and any isola through a measured orbit it
misses, or one branch per forcing frequency), and its JSON form."""

from __future__ import annotations

import numpy as np

from .._systems import AirspeedWindow
from ..data.orbit import OrbitDataset
from ..models.ude import UDE
from .continuation import trace_flutter, trace_flutter_through, trace_forced
from .diagram_type import MAIN, Diagram
from .metrics import branch_metrics, locations, model_orbit
from .metrics_type import ModelMetrics


def diagram_ranges(ds: OrbitDataset) -> dict:
    """Parameter and amplitude windows for tracing, from the data's own extent."""
    A = ds.amplitudes()
    if ds.kind.autonomous:
        window = AirspeedWindow.of(ds.parameters())
        return {"v_range": [window.low, window.high],
                "amp_max": ds.kind.amplitude_window * float(A.max())}
    out = {}
    for f in ds.frequencies_group():
        sub = ds.at_frequency(f)
        out[f"{f:g}"] = {"freq_hz": float(f), "a_range": [0.0, 1.3 * float(sub.parameters().max())],
                         "amp_max": ds.kind.amplitude_window * float(sub.amplitudes().max())}
    return {"frequencies": out}


def trace_diagram(model: UDE, ranges: dict, scales, ds: OrbitDataset | None = None) -> Diagram:
    """The model's branches (:class:`Diagram`).

    Aerofoil: the branch from the Hopf point; with ``ds``, also the branch through every
    measured orbit that branch does not explain (a fitted model can have isolas, which a
    continuation from the Hopf point alone would never see)."""
    if model.mech.autonomous:
        out = Diagram({MAIN: trace_flutter(model, v_range=ranges["v_range"],
                                           amp_max=ranges["amp_max"], scales=scales)})
        return out if ds is None else _with_isolas(model, out, ranges, scales, ds)
    out = {}
    for key, r in ranges["frequencies"].items():
        lo, hi = r["a_range"]
        out[r["freq_hz"]] = trace_forced(model, freq_hz=r["freq_hz"],
                                         a_range=(max(lo, 0.01 * hi), hi),
                                         amp_max=r["amp_max"], scales=scales)
    return Diagram(out)


def _with_isolas(model, diagram, ranges, scales, ds, max_isolas: int = 6, near: float = 0.02):
    start = ds.sample(1)
    a_max = float(ds.amplitudes().max())
    for i, o in enumerate(ds.orbits):
        if len(diagram) > max_isolas:
            break
        sol = model_orbit(model, diagram, o, scales=scales)
        if sol is not None and abs(sol["amplitude"] - o.amplitude) <= near * a_max:
            continue
        # hidden states (a refined model's lags) start at zero: Newton finds them, they
        # enter linearly
        y0 = np.concatenate([start["q"][i, 0], start["qdot"][i, 0], np.zeros(model.n_hidden)])
        def known(V, amp):
            return any(abs(a - amp) <= 5e-3 * a_max
                       for b in diagram.values() for a, _ in b.amplitudes_at(V))

        b = trace_flutter_through(model, y0, 1.0 / o.frequency, o.parameter,
                                  v_range=ranges["v_range"], amp_max=ranges["amp_max"],
                                  scales=scales, known=known)
        if b is not None and b.param.size > 1:
            diagram = diagram.with_isola(b)
    return diagram


def _evaluate(model, ds, ranges, scales, reference, ref_source) -> tuple[Diagram, ModelMetrics]:
    diagram = trace_diagram(model, ranges, scales, ds)
    return diagram, ModelMetrics.of(branch_metrics(model, diagram, ds, scales=scales),
                                    locations(diagram), reference, ref_source)
