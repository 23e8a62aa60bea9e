"""The whole offline job on one dataset: fit the mechanistic model and a UDE
(:func:`~ude_fit.fitting.fit`), then close the loop (explain the residual, add the
missing physics, refit; :func:`~ude_fit.discovery.loop.close_loop`).

:func:`run_pipeline` returns both results; :func:`~ude_fit.report.pipeline_files.
write_pipeline` writes them (``fit/``, ``loop/`` and the one summary). ``ude-fit pipeline``,
the lab's demo and the compose file's ``fit`` service run exactly this.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ._precision import require_float64
from .data.orbit import OrbitDataset
from .discovery.loop import LoopResult, close_loop
from .fitting import FitResult, fit
from .mechanistic_stage import with_chosen_zero
from .training.options import FitOptions


@dataclass(frozen=True)
class PipelineOptions:
    """Every option of the fit (:class:`FitOptions`, the same as ``ude-fit fit`` takes) and
    the loop's own. The loop uses the fit's system, seed and control input."""
    fit: FitOptions
    max_effects: int = 3        # most effects the loop adds
    min_gain: float = 0.1       # keep an effect only if the branch error falls by this
    bootstrap: int = 200        # bootstrap resamples for the loop's uncertainties
    locate_shapes: bool = True  # the loop also tries located shapes (not the catalogue only)

    def __post_init__(self):
        if not isinstance(self.fit, FitOptions):
            raise ValueError(f"fit must be a FitOptions, not {self.fit!r}")
        for name in ("max_effects", "bootstrap"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"--{name.replace('_', '-')} must be an integer at least 1, "
                                 f"not {v!r}")
        if self.fit.mechanistic_effects:
            # the loop chooses the effects itself, from the plain mechanistic model
            raise ValueError("--add applies to ude-fit fit only (the pipeline's loop adds "
                             "the effects it finds; ude-fit refine adds named ones)")
        if not isinstance(self.locate_shapes, bool):
            raise ValueError(f"locate_shapes must be true or false, not {self.locate_shapes!r}")
        if not (isinstance(self.min_gain, (int, float)) and math.isfinite(self.min_gain)
                and 0 <= self.min_gain < 1):
            raise ValueError(f"--min-gain must be at least 0 and below 1, not "
                             f"{self.min_gain!r}")

    def loop_json(self) -> dict:
        """The loop's options as its metrics.json records them."""
        return {"system": self.fit.system, "seed": self.fit.seed, "bootstrap": self.bootstrap,
                "max_effects": self.max_effects, "min_gain": self.min_gain,
                "locate_shapes": self.locate_shapes, "control_input": self.fit.control_input,
                "control_gain": self.fit.control_gain}

    def to_json(self) -> dict:
        return {"fit": self.fit.to_json(), "max_effects": self.max_effects,
                "locate_shapes": self.locate_shapes,
                "min_gain": self.min_gain, "bootstrap": self.bootstrap}


@dataclass
class PipelineResult:
    options: PipelineOptions
    fit: FitResult
    loop: LoopResult


def run_pipeline(ds: OrbitDataset, options: PipelineOptions, *,
                 progress=None) -> PipelineResult:
    """Fit, then close the loop, on ``ds``. ``progress(event=..., **fields)`` as for
    :func:`~ude_fit.fitting.fit` (with one ``stage`` event per part). JAX must run in
    float64 (``jax.config.update("jax_enable_x64", True)``; the command line does it)."""
    require_float64("run_pipeline")
    say = progress or (lambda **kw: None)
    opts = options.fit
    # the fit and the loop on one dataset about one rest position (where no file recorded
    # it, chosen once as the fit's options ask)
    ds = with_chosen_zero(ds, opts)
    say(event="stage", stage=f"pipeline 1/2: fit (mechanistic model and UDE, {opts.starts} "
        "starts)")
    fitted = fit(ds, opts, progress=progress)
    say(event="stage", stage="pipeline 2/2: close the loop (explain, add, refit)")
    loop = close_loop(ds, opts.system, max_effects=options.max_effects,
                      min_gain=options.min_gain, seed=opts.seed, bootstrap=options.bootstrap,
                      locate_shapes=options.locate_shapes, progress=progress,
                      control=opts.control())
    return PipelineResult(options, fitted, loop)
