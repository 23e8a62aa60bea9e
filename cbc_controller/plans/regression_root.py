"""The root of a noisy scalar function from repeated measurements: a local line fit.

Under process noise a single estimate of e(A*) (one block of the board's running
mean) scatters by a few per cent of the amplitude, and its scatter does not shrink
as the search closes in on the root. Regula falsi then converges onto the noise.
What noisy CBC does instead (Schilder et al. 2015, Renson et al. 2019) is to
regress many measurements on the target and take the regression's root; its
standard error says when enough has been measured. Here the measurements are
taken at the current root estimate itself: the slope, which a few blocks cannot
pin down, then only scales small offsets, and the curvature of e (steep on one
side of an unstable cycle) cannot bias the root. Pure functions, no rig.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LineRoot:
    root: float          # where the fitted line crosses zero
    slope: float         # de/dA at the root
    se: float            # standard error of the root (delta method)
    n: int               # measurements used
    residual_sd: float   # scatter of one measurement about the line


def fit_line_root(samples, centre: float, half_width: float) -> LineRoot | None:
    """Least-squares line e = c + s (A - centre) through the samples (A, e) with
    |A - centre| <= half_width; the root's standard error from the fit's covariance.
    None when the samples do not determine a line (fewer than 3, or a single target)."""
    pts = np.array([(a, e) for a, e in samples if abs(a - centre) <= half_width], dtype=float)
    if len(pts) < 3:
        return None
    x = pts[:, 0] - centre
    y = pts[:, 1]
    if np.ptp(x) <= 0.0:
        return None
    X = np.column_stack([np.ones_like(x), x])
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    c, s = float(coef[0]), float(coef[1])
    if s == 0.0:
        return None
    dof = len(pts) - 2
    res = y - X @ coef
    sd = math.sqrt(float(res @ res) / dof) if dof > 0 else 0.0
    cov = sd ** 2 * np.linalg.inv(X.T @ X)
    x0 = -c / s                                   # root relative to the centre
    # root = centre - c/s: gradient (-1/s, c/s^2) with respect to (c, s)
    g = np.array([-1.0 / s, c / s ** 2])
    se = math.sqrt(max(float(g @ cov @ g), 0.0))
    return LineRoot(root=centre + x0, slope=s, se=se, n=len(pts), residual_sd=sd)


def root_from_blocks(samples, centre: float, step: float, slope: float,
                     block_sd: float, min_slope: float = 0.0) -> LineRoot | None:
    """The root from blocks measured near `centre`: each block (A, e) within 1.5 step
    of it gives A - e / slope; the root is their mean. The slope is refitted from
    the blocks within 4 steps when they determine it with the same sign, else the
    given one is kept; its magnitude is held at `min_slope` or more (e can be flat
    on one side of a root, where a fitted slope near zero would throw the root far
    away). The standard error takes the larger of the blocks' own scatter and
    `block_sd`, the scatter known from all blocks at this parameter."""
    wide = fit_line_root(samples, centre, 4 * step)
    if wide is not None and wide.slope * slope > 0:
        slope = wide.slope
    if abs(slope) < min_slope:
        slope = math.copysign(min_slope, slope)
    near = np.array([(a, e) for a, e in samples if abs(a - centre) <= 1.5 * step], dtype=float)
    if len(near) < 3 or slope == 0.0:
        return None
    roots = near[:, 0] - near[:, 1] / slope
    sd = max(float(roots.std(ddof=1)), block_sd / abs(slope))
    se = sd / math.sqrt(len(roots))
    # consecutive blocks at one target are correlated (the closed loop's slow amplitude
    # mode outlives a block), so the blocks' scatter understates the mean's error: the
    # scatter of the per-target means, which sees that correlation, bounds it too
    targets = np.unique(near[:, 0])
    if len(targets) >= 3:
        means = np.array([roots[near[:, 0] == a].mean() for a in targets])
        se = max(se, float(means.std(ddof=1)) / math.sqrt(len(means)))
    return LineRoot(root=float(roots.mean()), slope=float(slope), se=se, n=len(roots),
                    residual_sd=sd * abs(slope))


def pooled_sd(groups) -> float | None:
    """Pooled within-group standard deviation of repeated measurements (one group
    per target); None with no group of two or more."""
    ss, dof = 0.0, 0
    for g in groups:
        g = np.asarray(g, dtype=float)
        if len(g) >= 2:
            ss += float(((g - g.mean()) ** 2).sum())
            dof += len(g) - 1
    return math.sqrt(ss / dof) if dof else None
