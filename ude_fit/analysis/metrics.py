"""How well a model's bifurcation diagram matches the measured orbits (DESIGN.md definitions).

* Branch amplitude error: for every measured orbit, the model's orbit at the same parameter
  on the part of the diagram with the measured stability (the crossing nearest in
  amplitude), solved exactly, and |model amplitude - measured amplitude| divided by the
  largest measured amplitude. RMS and max over the points found; a point the model has no
  orbit for (no crossing with that stability) is *missed*.
  Near a fold the amplitude at a fixed parameter is ill-conditioned: a campaign that
  refines a fold measures points a hair from it, and a model whose fold sits 0.05 % short
  would be compared on its other branch (or miss the point) although its diagram passes
  through the point. So a model fold within ``FOLD_TOLERANCE`` of the parameter span of the
  point, on a branch of the point's stability, is a candidate too (the point is compared
  with the orbit at the fold, marked ``at_fold``), and the nearest candidate in amplitude
  wins. Points on a branch the model has are unaffected.
* Hopf and fold: the model's locations, and their errors against a reference (the truth
  where a test knows it, otherwise an estimate from the measured points, which says so).
* Trajectory error: the model orbit and the measured one over one period, after the phase
  shift that aligns them best, RMS over the positions, each divided by its largest
  measured amplitude; then RMS over the points.
"""

from __future__ import annotations

import numpy as np

from .._fourier import K, harmonics
from ..data.orbit import OrbitDataset
from .continuation import orbit_at, same_fold
from .diagram_type import Diagram
from .metrics_type import BranchErrors, PointError


def _series(coeffs):
    """(n_coord, 15) -> complex (n_coord, K) with x = sum Re(C_k e^{i k phi})."""
    c = np.asarray(coeffs, float)
    return c[:, 1:K + 1] - 1j * c[:, K + 1:], c[:, 0]


def aligned_rms(model_coeffs, data_coeffs, scale) -> float:
    """RMS over one period of (model - data) / scale after the best phase shift of the model
    (grid of 720 shifts, then a parabolic refinement); all coordinates together."""
    Cm, dm = _series(model_coeffs)
    Cd, dd = _series(data_coeffs)
    k = np.arange(1, K + 1)
    w = 1.0 / np.asarray(scale, float)[:, None]

    def err(s):
        diff = (Cm * np.exp(1j * k * s) - Cd) * w
        # mean over a period of a Fourier series: DC^2 + sum |C_k|^2 / 2
        return (np.sum(((dm - dd) * w[:, 0]) ** 2) + 0.5 * np.sum(np.abs(diff) ** 2)) / len(w)

    grid = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    e = np.array([err(s) for s in grid])
    j = int(np.argmin(e))
    h = grid[1] - grid[0]
    a, b, c = e[j - 1], e[j], e[(j + 1) % len(e)]
    den = a - 2 * b + c
    s = grid[j] + (0.5 * h * (a - c) / den if den > 0 else 0.0)
    return float(np.sqrt(max(min(err(s), b), 0.0)))


FOLD_TOLERANCE = 0.01      # of the measured parameter span: see the module docstring


def branch_metrics(model, diagram: dict, ds: OrbitDataset, *, scales) -> BranchErrors:
    """Branch amplitude and trajectory errors of ``model`` (whose traced branches are
    ``diagram``: {"flutter": Branch} or {frequency_hz: Branch}) against the dataset."""
    amps = ds.amplitudes()
    a_max = float(amps.max())
    params = [o.parameter for o in ds.orbits]
    fold_tol = FOLD_TOLERANCE * (max(params) - min(params))
    n_pos = model.mech.n_dof
    pos_scale = np.array([max(np.hypot(o.coeffs[i][1], o.coeffs[i][K + 1])
                              for o in ds.orbits) for i in range(n_pos)])
    points = []
    for o in ds.orbits:
        measured = dict(parameter=o.parameter, frequency=o.frequency, measured=o.amplitude,
                        stable=o.stable)
        sol = model_orbit(model, diagram, o, scales=scales, fold_tolerance=fold_tol)
        if sol is None or (o.stable is not None and not sol.get("at_fold")
                           and sol["stable"] != o.stable):
            points.append(PointError(**measured))
            continue
        hc = np.asarray(harmonics(sol["samples"][:, :n_pos]))      # (n_pos, 15)
        points.append(PointError(
            **measured, model=sol["amplitude"], error=abs(sol["amplitude"] - o.amplitude) / a_max,
            trajectory=aligned_rms(hc, np.asarray(o.coeffs)[:n_pos], pos_scale),
            model_stable=sol["stable"],
            model_parameter=sol["parameter"] if sol.get("at_fold") else None))
    return BranchErrors.of(points, a_max, ds.frequencies_group() if ds.kind.forced else None)


def model_orbit(model, diagram: dict, o, *, scales,
                fold_tolerance: float | None = None) -> dict | None:
    """The model's orbit matching measured orbit ``o``: same parameter, the measured
    stability, nearest in amplitude over all branches (see _continuation.orbit_at).
    With ``fold_tolerance`` (parameter units), the orbits at the model's folds within that
    distance of ``o``'s parameter, next to a part of the branch with ``o``'s stability,
    compete too (returned with ``at_fold`` and the fold's ``parameter``)."""
    best = None

    def better(sol):
        return best is None or (abs(sol["amplitude"] - o.amplitude)
                                < abs(best["amplitude"] - o.amplitude))

    for b in Diagram.of(diagram).branches_for_orbit(o):
        sol = orbit_at(model, b, o.parameter, o.stable, scales=scales, near=o.amplitude)
        if sol is None or (o.stable is not None and sol["stable"] != o.stable):
            continue
        if better(sol):
            best = sol
    if not fold_tolerance:
        return best
    for b in Diagram.of(diagram).branches_for_orbit(o):
        for f in b.folds:
            if abs(f["param"] - o.parameter) > fold_tolerance:
                continue
            if best is not None and abs(f["amplitude"] - o.amplitude) >= abs(
                    best["amplitude"] - o.amplitude):
                continue
            k = int(np.argmin(np.abs(b.param - f["param"]) + np.abs(b.amplitude
                                                                    - f["amplitude"])))
            sides = {bool(b.stable[j]) for j in (max(k - 1, 0), min(k + 1, len(b.param) - 1))}
            if o.stable is not None and o.stable not in sides:
                continue
            # the fold itself lies between traced points (it is located beyond them):
            # its amplitude is the located one, its orbit that of the nearest traced point
            sol = orbit_at(model, b, float(b.param[k]), None, scales=scales,
                           near=float(b.amplitude[k]))
            if sol is None:
                continue
            # the fold's stability is the side the point is compared with: the nearest
            # traced orbit may lie on the other side of the fold
            sol = {**sol, "amplitude": float(f["amplitude"]), "at_fold": True,
                   "parameter": float(f["param"]),
                   "stable": o.stable if o.stable is not None else sol["stable"]}
            if better(sol):
                best = sol
    return best


def _counted_folds(diagram: Diagram) -> tuple[list, list]:
    """A self-excited diagram's folds as counted: the main branch's, and the isolas' not
    already counted. An isola traced from a measured orbit can be a stretch of a branch
    already traced (the two met only beyond the point the tracing started from): its
    folds are those already counted."""
    seen, others = list(diagram.main.folds), []
    for bb in diagram.isolas:
        for f in bb.folds:
            if not any(same_fold(f, g) for g in seen):
                seen.append(f)
                others.append(f)
    return list(diagram.main.folds), others


def locations(diagram: dict) -> dict:
    """Hopf and fold parameters of a traced diagram (None where there is none)."""
    diagram = Diagram.of(diagram)
    b = diagram.main
    if b is not None:
        hopf = b.hopf["param"] if b.hopf else None
        main, isola = _counted_folds(diagram)
        folds = sorted(f["param"] for f in main)
        others = sorted(f["param"] for f in isola)
        return {"hopf": hopf, "fold": folds[0] if folds else None, "folds": folds,
                "isolas": len(diagram.isolas), "isola_folds": others}
    return {"hopf": None, "fold": None,
            "folds": {f"{float(f):g}": sorted(x["param"] for x in b.folds)
                      for f, b in diagram.items()}}


def fold_points(diagram: dict) -> list[dict] | dict[str, list[dict]]:
    """Where a diagram's counted folds are, by amplitude: ``{"param", "amplitude",
    "isola"}`` for each (self-excited), or per forcing frequency ``{"param",
    "amplitude"}`` (forced). The same folds :func:`locations` counts."""
    diagram = Diagram.of(diagram)
    point = lambda f: {"param": float(f["param"]), "amplitude": float(f["amplitude"])}
    if diagram.main is not None:
        main, isola = _counted_folds(diagram)
        pts = [{**point(f), "isola": False} for f in main]
        pts += [{**point(f), "isola": True} for f in isola]
        return sorted(pts, key=lambda f: f["amplitude"])
    return {f"{float(k):g}": sorted((point(f) for f in b.folds), key=lambda f: f["amplitude"])
            for k, b in diagram.items()}
