"""The optimiser loop: Adam (optax), then L-BFGS (:mod:`.lbfgs`, on the host), all float64,
on any loss of (params, *args). Compiled functions are shared by every call with the same
loss and argument structure.

:func:`minimize` optimises one set of parameters; :func:`descend` with ``lanes`` optimises
N independent sets (every leaf with a leading axis of N, one *lane* per random start).
Adam runs the lanes together, its step vmapped over them, optimiser state included: the
integrations are long chains of small operations, and a batch shares their per-operation
cost (on 2 cores a periodic step costs 12.6 ms per lane in a batch of 16, 18.4 ms alone;
beyond four lanes the arithmetic sets the cost, docs/experiments.md). One set's Adam steps
and every L-BFGS evaluation call one compiled value-and-gradient of the loss
(:data:`.lbfgs.value_and_grad`), so a loss is compiled once for both optimisers. L-BFGS
runs each lane alone: its line search takes as many evaluations as the lane needs. Lanes
never interact: a lane's result is the single run's on its parameters, to rounding. A lane
whose loss goes non-finite in Adam is dropped (its reason recorded) and from then on carries
a copy of a live lane, so no NaN runs through the batch.
"""

from __future__ import annotations

import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from . import lbfgs
from .lbfgs import value_and_grad


class Diverged(RuntimeError):
    """Training produced a non-finite loss; the start is dropped."""


_ADAM_CHUNK = 25
_OPTIMISERS: dict = {}


def _adam(lr):
    if ("adam", lr) not in _OPTIMISERS:
        _OPTIMISERS[("adam", lr)] = optax.adam(lr)
    return _OPTIMISERS[("adam", lr)]


def _adam_scan(params, state, loss, args, opt):
    def body(carry, _):
        p, s = carry
        val, g = jax.value_and_grad(loss)(p, *args)
        u, s = opt.update(g, s, p)
        return (optax.apply_updates(p, u), s), val
    (params, state), vals = jax.lax.scan(body, (params, state), None, length=_ADAM_CHUNK)
    return params, state, vals[-1]


def _over_lanes(step):
    """``step`` vmapped over the lanes of params and state (args shared), compiled."""
    @eqx.filter_jit
    def batched(params, state, loss, args, opt):
        return eqx.filter_vmap(lambda p, s: step(p, s, loss, args, opt))(params, state)
    return batched


_ADAM_LANES = _over_lanes(_adam_scan)


def _adam_apply(grad, state, params, opt):
    u, state = opt.update(grad, state, params)
    return optax.apply_updates(params, u), state


_ADAM_APPLY = eqx.filter_jit(_adam_apply)


def _adam_chunk(params, state, loss, args, opt):
    """:data:`_ADAM_CHUNK` Adam steps on one set: the loss's compiled value-and-gradient
    (the one L-BFGS calls) and a compiled update, dispatched step by step without waiting."""
    for _ in range(_ADAM_CHUNK):
        val, g = value_and_grad(params, loss, args)
        params, state = _ADAM_APPLY(g, state, params, opt)
    return params, state, val


def _refill(live: np.ndarray, *trees):
    """The trees with every lane that is not ``live`` replaced by a copy of a live one."""
    idx = np.where(live, np.arange(live.size), int(np.argmax(live)))
    return tuple(jax.tree_util.tree_map(lambda x: x[idx] if eqx.is_array(x) else x, t)
                 for t in trees)


def lane_of(tree, i: int):
    """Lane i of a tree of stacked lanes."""
    return jax.tree_util.tree_map(lambda x: x[i] if eqx.is_array(x) else x, tree)


def _put_lanes(tree, lanes: list):
    """``tree`` with lane i replaced by each (i, one-lane tree) in ``lanes``."""
    idx = np.array([i for i, _ in lanes])

    def put(x, *ones):
        if not eqx.is_array(x):
            return x
        return x.at[idx].set(jnp.stack(ones))
    return jax.tree_util.tree_map(put, tree, *(one for _, one in lanes))


def _lbfgs_run(loss, params, args, steps: int, on_step):
    """L-BFGS on one set of parameters. Returns (params, loss, reason): reason is None,
    or why it failed (the loss not finite at its first step)."""
    flat = lbfgs.Flat(params)

    def evaluate(x):
        v, g = value_and_grad(flat.tree(x), loss, args)
        return float(v), flat.vector(g)
    r = lbfgs.run(evaluate, flat.vector(params), steps, on_step)
    return flat.tree(r.x), r.value, r.reason


def descend(loss, params, args, *, lanes: int | None, adam_steps: int, lbfgs_steps: int,
            lr: float, failed: dict | None = None, progress=None, stage: str = ""):
    """Adam then L-BFGS on ``loss(params, *args)``.

    ``lanes``: None for one set of parameters; else the number of independent sets that
    ``params`` holds along its leading axis (``args`` shared), optimised together.
    ``failed`` (lane -> reason, lane 0 for a single set): lanes already failed (in an
    earlier stage); they are carried but not optimised. Returns (params, losses, failed):
    a loss per lane (NaN on failed lanes, whose parameters are meaningless) and the
    failures including this stage's. A lane fails when its loss is not finite in Adam or
    at the first L-BFGS step; later in L-BFGS a trial point where it is not finite is a
    step too long (:mod:`.lbfgs`)."""
    n = lanes or 1
    adam_steps_of = _adam_chunk if lanes is None else _ADAM_LANES
    failed = dict(failed or {})
    live = np.array([i not in failed for i in range(n)])
    vals = np.full(n, np.nan)
    t0 = time.perf_counter()

    def report(optimiser, step, steps, going):
        # one event for all lanes: the best loss, and every lane's where there are several
        if progress and going.any():
            extra = {} if lanes is None else {"losses": vals.tolist(), "lanes": n}
            progress(stage=stage, optimiser=optimiser, step=step, steps=steps,
                     loss=float(np.min(vals[going])), elapsed=time.perf_counter() - t0,
                     **extra)

    def lose(lanes_now, reason):
        for i in np.flatnonzero(lanes_now):
            failed.setdefault(int(i), reason)

    if adam_steps > 0 and live.any():
        opt = _adam(lr)
        state = (opt.init(params) if lanes is None
                 else eqx.filter_vmap(opt.init)(params))
        for done in range(_ADAM_CHUNK, adam_steps + _ADAM_CHUNK, _ADAM_CHUNK):
            params, state, v = adam_steps_of(params, state, loss, args, opt)
            v = np.atleast_1d(np.asarray(v, float))
            bad = live & ~np.isfinite(v)
            lose(bad, f"{stage}: loss is not finite at Adam step {done}")
            live &= ~bad
            vals[live] = v[live]
            if not live.any():
                break
            if bad.any():
                params, state = _refill(live, params, state)
            report("adam", min(done, adam_steps), adam_steps, live)
    if lbfgs_steps > 0 and live.any():
        # one lane at a time, each on the host around the compiled value and gradient
        done = []
        for i in (np.flatnonzero(live) if lanes is not None else [0]):
            one = params if lanes is None else lane_of(params, int(i))

            def on_step(k, v, i=i):
                vals[i] = v
                report("lbfgs", k, lbfgs_steps, np.arange(n) == i)
            one, vals[i], reason = _lbfgs_run(loss, one, args, lbfgs_steps, on_step)
            if reason is not None:
                failed.setdefault(int(i), f"{stage}: {reason}")
            done.append((int(i), one))
        params = done[0][1] if lanes is None else _put_lanes(params, done)
    vals[list(failed)] = np.nan
    return params, vals, failed


def minimize(loss, params, args, *, adam_steps: int, lbfgs_steps: int, lr: float,
             progress=None, stage: str = ""):
    """:func:`descend` on one set of parameters; returns (params, final loss); raises
    :class:`Diverged` where it fails."""
    params, vals, failed = descend(loss, params, args, lanes=None, adam_steps=adam_steps,
                                   lbfgs_steps=lbfgs_steps, lr=lr, progress=progress,
                                   stage=stage)
    if failed:
        raise Diverged(failed[0])
    return params, float(vals[0])
