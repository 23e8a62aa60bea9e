"""Fitted models on disk: one file, a JSON header line and then equinox-serialised leaves.

The header says everything needed to rebuild the pytree's skeleton (system, mechanistic
parameters, the correction's kind and shape) plus what the fit recorded (options, data
sources, scales, tracing ranges, traced diagrams, version), so ``ude-fit diagram MODEL``
can redraw without the data and re-trace without guessing.
"""

from __future__ import annotations

import io
import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .data.orbit import DataError
from .models.amplitude import AmplitudeCorrection, SizeBasis
from .models.corrections import (MLPCorrection, PolynomialParamCorrection,
                                 RestFreeCorrection, Scaling)
from .models.mechanistic import SYSTEMS, parameters_of
from .models.refined import describe, refined
from .models.ude import UDE
from .training.gp import GPCorrection


MAGIC = "ude_fit-model"
FORMAT_VERSION = 1


def _version() -> str:
    try:
        from importlib.metadata import version
        return version("virtual-cbc-lab")
    except Exception:  # noqa: BLE001 - running from a source tree without metadata
        return "unknown"


def _correction_header(c) -> dict | None:
    if c is None:
        return None
    if isinstance(c, RestFreeCorrection):
        return {"kind": "rest-free", "n_dof": int(c.n_dof),
                "inner": _correction_header(c.inner)}
    if isinstance(c, MLPCorrection):
        lin = [l for l in c.mlp.layers]
        return {"kind": "mlp", "n_in": int(c.mlp.in_size), "n_out": int(c.mlp.out_size),
                "width": int(c.mlp.width_size), "depth": int(c.mlp.depth),
                "layers": len(lin)}
    if isinstance(c, PolynomialParamCorrection):
        # n_in/n_out are the correction's (states and parameter in, forces out), not the
        # network's, which sees the states and has one head per power of the parameter
        return {"kind": "mlp-polynomial", "n_in": int(c.mlp.in_size) + 1,
                "n_out": int(c.mlp.out_size) // (c.degree + 1), "degree": int(c.degree),
                "width": int(c.mlp.width_size), "depth": int(c.mlp.depth)}
    if isinstance(c, AmplitudeCorrection):
        return {"kind": "amplitude", "n_dof": int(c.n_dof),
                "n_in": int(c.scaling.z_mean.shape[0]), "knots": int(c.basis.knots.shape[0])}
    if isinstance(c, GPCorrection):
        return {"kind": "gp", "N": int(c.Z.shape[0]), "d": int(c.Z.shape[1]),
                "m": int(c.alpha.shape[1])}
    raise TypeError(f"cannot save a correction of type {type(c).__name__}")


def _skeleton_correction(h: dict | None):
    if h is None:
        return None
    if h["kind"] == "rest-free":
        return RestFreeCorrection(_skeleton_correction(h["inner"]), h["n_dof"])
    if h["kind"] == "mlp":
        sc = Scaling(jnp.zeros(h["n_in"]), jnp.ones(h["n_in"]), jnp.ones(h["n_out"]))
        return MLPCorrection(h["n_in"], h["n_out"], sc, width=h["width"], depth=h["depth"],
                             key=jax.random.PRNGKey(0))
    if h["kind"] == "mlp-polynomial":
        sc = Scaling(jnp.zeros(h["n_in"]), jnp.ones(h["n_in"]), jnp.ones(h["n_out"]))
        return PolynomialParamCorrection(h["n_in"], h["n_out"], sc, degree=h["degree"],
                                         width=h["width"], depth=h["depth"],
                                         key=jax.random.PRNGKey(0))
    if h["kind"] == "amplitude":
        n, k = h["n_dof"], h["knots"]
        sc = Scaling(jnp.zeros(h["n_in"]), jnp.ones(h["n_in"]), jnp.ones(n))
        return AmplitudeCorrection(n, sc, SizeBasis(jnp.zeros(k), jnp.ones(k)),
                                   key=jax.random.PRNGKey(0))
    if h["kind"] == "gp":
        N, d, m = h["N"], h["d"], h["m"]
        z = lambda *s: jnp.zeros(s)
        return GPCorrection(Z=z(N, d), alpha=z(N, m), log_lengthscales=z(m, d),
                            log_signal=z(m), log_noise=z(m), z_mean=z(d), z_scale=z(d),
                            y_mean=z(m), y_scale=z(m), chol=None)
    raise DataError(f"unknown correction kind {h['kind']!r} in the model file")


def save_model(path, model: UDE, **meta) -> None:
    """Write ``model`` and JSON-able ``meta`` (options, scales, ranges, diagrams...) to ``path``."""
    mech = model.mech
    header = {"format": MAGIC, "format_version": FORMAT_VERSION, "version": _version(),
              "system": model.system, "mechanistic": parameters_of(mech.base),
              "effects": describe(mech),
              "correction": _correction_header(model.correction), **meta}
    buf = io.BytesIO()
    eqx.tree_serialise_leaves(buf, model)
    line = json.dumps(header, default=_jsonable).encode()
    with open(path, "wb") as fh:
        fh.write(line + b"\n")
        fh.write(buf.getvalue())


def _jsonable(x):
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    raise TypeError(f"not JSON-serialisable: {type(x).__name__}")


def load_model(path) -> tuple[UDE, dict]:
    """Read a model written by :func:`save_model`: (UDE, header). DataError if it is not one."""
    try:
        with open(path, "rb") as fh:
            first = fh.readline(10_000_000)
            rest = fh.read()
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror or exc})") from None
    try:
        header = json.loads(first)
        ok = isinstance(header, dict) and header.get("format") == MAGIC
    except (ValueError, UnicodeDecodeError):
        ok = False
    if not ok:
        raise DataError(f"{path}: not a ude_fit model file")
    if header.get("format_version") != FORMAT_VERSION:
        raise DataError(f"{path}: model file format {header.get('format_version')} "
                        f"(this ude_fit reads {FORMAT_VERSION})")
    system = header.get("system")
    if system not in SYSTEMS:
        raise DataError(f"{path}: unknown system {system!r} in the model file")
    mech = SYSTEMS[system].nominal(**header["mechanistic"])
    if header.get("effects"):
        try:
            mech = refined(mech, header["effects"])
        except (ValueError, KeyError, TypeError) as exc:
            raise DataError(f"{path}: bad effect in the model file ({exc})") from None
    skeleton = UDE(mech, _skeleton_correction(header.get("correction")))
    try:
        model = eqx.tree_deserialise_leaves(io.BytesIO(rest), skeleton)
    except Exception as exc:  # noqa: BLE001 - any decoding problem is a damaged file
        raise DataError(f"{path}: model file is damaged ({type(exc).__name__})") from None
    return model, header
