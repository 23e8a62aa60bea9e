"""Offline fitting of mechanistic and universal-differential-equation models to limit cycles."""
import jax as _jax

# Fitting and continuation need float64; ude_fit switches JAX to it on import.
_jax.config.update("jax_enable_x64", True)
