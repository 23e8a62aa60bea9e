"""The optimiser loop: Adam, then L-BFGS (optax), all float64, on any loss of
(params, *args). Compiled steps are shared by every call with the same loss and
argument structure.

:func:`minimize` optimises one set of parameters; :func:`minimize_ensemble` optimises
N independent sets at once (every leaf with a leading axis of N, one *lane* per random
start): each step is the single step vmapped over the lanes, optimiser state included,
so on a CPU the N starts cost little more than one (the integrations are long chains of
small operations whose cost is per operation, not per number). Lanes never interact: a
lane's result is the single run's on its parameters, to rounding. A lane whose loss goes
non-finite is dropped (its reason recorded) and from then on carries a copy of a live
lane, so no NaN runs through the batch and slows its line searches.
"""

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


def _adam_scan(params, state, loss, args, opt):
    def body(carry, _):
        p, s = carry
        val, g = jax.value_and_grad(loss)(p, *args)
        u, s = opt.update(g, s, p)
        return (optax.apply_updates(p, u), s), val
    (params, state), vals = jax.lax.scan(body, (params, state), None, length=_ADAM_CHUNK)
    return params, state, vals[-1]


def _lbfgs_update(params, state, loss, args, opt):
    f = lambda p: loss(p, *args)
    vg = optax.value_and_grad_from_state(f)
    val, g = vg(params, state=state)
    u, state = opt.update(g, state, params, value=val, grad=g, value_fn=f)
    return optax.apply_updates(params, u), state, val


def _over_lanes(step):
    """``step`` vmapped over the lanes of params and state (args shared), compiled."""
    @eqx.filter_jit
    def batched(params, state, loss, args, opt):
        return eqx.filter_vmap(lambda p, s: step(p, s, loss, args, opt))(params, state)
    return batched


# (one set of parameters, a batch of lanes)
_STEPS = {"adam": (eqx.filter_jit(_adam_scan), _over_lanes(_adam_scan)),
          "lbfgs": (eqx.filter_jit(_lbfgs_update), _over_lanes(_lbfgs_update))}


def _strong_types(tree):
    """The same values without JAX's weak types: optax.lbfgs's fresh state holds weakly
    typed scalars that its first update returns strongly typed, so without this the step
    is compiled twice (several seconds for a shooting loss)."""
    return jax.tree_util.tree_map(
        lambda x: jnp.array(x, dtype=x.dtype) if isinstance(x, jax.Array) else x, tree)


def _select(mask, new, old):
    """Per lane, ``new`` where ``mask`` else ``old`` (mask 0-d for a single run)."""
    mask = jnp.asarray(mask)

    def pick(a, b):
        if not eqx.is_array(a):
            return a
        return jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - mask.ndim)), a, b)
    return jax.tree_util.tree_map(pick, new, old)


def _refill(live: np.ndarray, *trees):
    """The trees with every lane that is not ``live`` replaced by a copy of a live one."""
    idx = np.where(live, np.arange(live.size), int(np.argmax(live)))
    return tuple(jax.tree_util.tree_map(lambda x: x[idx] if eqx.is_array(x) else x, t)
                 for t in trees)


def descend(loss, params, args, *, lanes: int | None, adam_steps: int, lbfgs_steps: int,
            lr: float, failed: dict | None = None, progress=None, stage: str = ""):
    """Adam then L-BFGS on ``loss(params, *args)``.

    ``lanes``: None for one set of parameters; else the number of independent sets that
    ``params`` holds along its leading axis (``args`` shared), optimised together.
    ``failed`` (lane -> reason, lane 0 for a single set): lanes already failed (in an
    earlier stage); they are carried but not optimised. Returns (params, losses, failed):
    a loss per lane (NaN on failed lanes, whose parameters are meaningless) and the
    failures including this stage's. A lane fails when its loss is not finite in Adam or
    at the first L-BFGS step; later in L-BFGS it stops at its best point instead."""
    n = lanes or 1
    which = 0 if lanes is None else 1          # index into _STEPS' pairs
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
            params, state, v = _STEPS["adam"][which](params, state, loss, args, opt)
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
        opt = _lbfgs()
        state = _strong_types(opt.init(params) if lanes is None
                              else eqx.filter_vmap(opt.init)(params))
        best_val, best = np.full(n, np.inf), params
        running = live.copy()           # lanes still stepping
        stopped = np.zeros(n, bool)     # lanes that went non-finite after a finite step
        for k in range(1, lbfgs_steps + 1):
            new, state, v = _STEPS["lbfgs"][which](params, state, loss, args, opt)
            v = np.atleast_1d(np.asarray(v, float))   # the loss at ``params``
            bad = running & ~np.isfinite(v)
            # a lane that had a finite step stops at its best; one that never had fails
            stopped |= bad & np.isfinite(best_val)
            lose(bad & ~np.isfinite(best_val),
                 f"{stage}: loss is not finite at L-BFGS step {k}")
            running &= ~bad
            better = running & (v < best_val)
            best_val = np.where(better, v, best_val)
            best = _select(better if lanes is not None else bool(better[0]), params, best)
            vals[running] = v[running]
            params = new
            if not running.any():
                break
            if bad.any():
                params, state = _refill(running, params, state)
            if k % 10 == 0 or k == lbfgs_steps:
                report("lbfgs", k, lbfgs_steps, running)
        if stopped.any():
            params = _select(stopped if lanes is not None else True, best, params)
            vals[stopped] = best_val[stopped]
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
