"""ude_fit computes in float64 (stiff shooting, Newton on periodic orbits, monodromy
determinants) but leaves JAX's global settings to the program that uses it: the command
line switches float64 on; a library user does it once, before any array is made::

    import jax
    jax.config.update("jax_enable_x64", True)

The long jobs check it (:func:`require_float64`) rather than run in float32 quietly."""

from __future__ import annotations

import jax


def require_float64(what: str) -> None:
    if not jax.config.jax_enable_x64:
        raise RuntimeError(f"{what} needs JAX in float64: call "
                           "jax.config.update('jax_enable_x64', True) first (the ude-fit "
                           "command does)")
