"""The optimiser loop: Adam, then L-BFGS (optax), all float64, on any loss of
(params, *args). Compiled steps are shared by every call with the same loss and
argument structure (every random start of a fit)."""

from __future__ import annotations

import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax


class Diverged(RuntimeError):
    """Training produced a non-finite loss; the start is dropped."""


_ADAM_CHUNK = 25
_OPTIMISERS: dict = {}


def _adam(lr):
    if ("adam", lr) not in _OPTIMISERS:
        _OPTIMISERS[("adam", lr)] = optax.adam(lr)
    return _OPTIMISERS[("adam", lr)]


def _lbfgs():
    if "lbfgs" not in _OPTIMISERS:
        _OPTIMISERS["lbfgs"] = optax.lbfgs()
    return _OPTIMISERS["lbfgs"]


@eqx.filter_jit
def _adam_chunk(params, state, loss, args, opt):
    def body(carry, _):
        p, s = carry
        val, g = jax.value_and_grad(loss)(p, *args)
        u, s = opt.update(g, s, p)
        return (optax.apply_updates(p, u), s), val
    (params, state), vals = jax.lax.scan(body, (params, state), None, length=_ADAM_CHUNK)
    return params, state, vals[-1]


def _strong_types(tree):
    """The same values without JAX's weak types: optax.lbfgs's fresh state holds weakly
    typed scalars that its first update returns strongly typed, so without this the step
    is compiled twice (several seconds for a shooting loss)."""
    return jax.tree_util.tree_map(
        lambda x: jnp.array(x, dtype=x.dtype) if isinstance(x, jax.Array) else x, tree)


@eqx.filter_jit
def _lbfgs_step(params, state, loss, args, opt):
    f = lambda p: loss(p, *args)
    vg = optax.value_and_grad_from_state(f)
    val, g = vg(params, state=state)
    u, state = opt.update(g, state, params, value=val, grad=g, value_fn=f)
    return optax.apply_updates(params, u), state, val


def minimize(loss, params, args, *, adam_steps: int, lbfgs_steps: int, lr: float,
             progress=None, stage: str = ""):
    """Adam then L-BFGS on ``loss(params, *args)``; raises :class:`Diverged` on NaN."""
    t0 = time.perf_counter()
    val = float("nan")
    if adam_steps > 0:
        opt = _adam(lr)
        state = opt.init(params)
        for done in range(_ADAM_CHUNK, adam_steps + _ADAM_CHUNK, _ADAM_CHUNK):
            params, state, v = _adam_chunk(params, state, loss, args, opt)
            val = float(v)
            if not np.isfinite(val):
                raise Diverged(f"{stage}: loss is not finite at Adam step {done}")
            if progress:
                progress(stage=stage, optimiser="adam", step=min(done, adam_steps),
                         steps=adam_steps, loss=val, elapsed=time.perf_counter() - t0)
    if lbfgs_steps > 0:
        opt = _lbfgs()
        state = _strong_types(opt.init(params))
        best = (np.inf, params)
        for k in range(1, lbfgs_steps + 1):
            params, state, v = _lbfgs_step(params, state, loss, args, opt)
            val = float(v)
            if not np.isfinite(val):
                if np.isfinite(best[0]):
                    params, val = best[1], best[0]
                    break
                raise Diverged(f"{stage}: loss is not finite at L-BFGS step {k}")
            if val < best[0]:
                best = (val, params)
            if progress and (k % 10 == 0 or k == lbfgs_steps):
                progress(stage=stage, optimiser="lbfgs", step=k, steps=lbfgs_steps, loss=val,
                         elapsed=time.perf_counter() - t0)
    return params, val


