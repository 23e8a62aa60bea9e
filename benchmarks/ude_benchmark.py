"""ude_fit benchmark figures (JSON on stdout): fit time to 1 % branch error, continuation time
per branch, 16 starts trained as one vectorised ensemble and one after another (wall,
training and compile time, each start's loss and branch error), periodic-orbit against trajectory training, and how the error and the
apparent Hopf point move with measurement noise for the NN and the GP corrections.

    python3 benchmarks/ude_benchmark.py [--quick] [--only ensemble|step|cache] [--starts N]
                                        [--out F.json]

Data: the aerofoil rig's true limit cycles written in the campaign layout by the test fixture
(tests/ude_fixtures.py), σ = 0 (averaged truth) or σ > 0 (a held orbit, noisy raw record,
Fourier-averaged by the loader). Truth Hopf/fold from the rig's own continuation. Every fit
runs in a fresh subprocess so compilation is counted where the figure says so. Medians over
``--repeat`` runs where a figure is a time.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time

import jax  # noqa: E402  (after the imports above, before any array)

jax.config.update("jax_enable_x64", True)       # ude_fit computes in float64 (see ude_fit docs)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

AIRSPEEDS_10 = (18.0, 19.5, 21.0, 22.5, 23.6)          # 10 orbits: 5 stable, 5 unstable
AIRSPEEDS_16 = (17.0, 18.0, 19.0, 20.0, 21.0, 22.0, 23.0, 23.6)


_COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration",
                   "/jax/core/compile/jaxpr_to_mlir_module_duration",
                   "/jax/core/compile/backend_compile_duration")


def _count_compilation() -> dict:
    """Seconds JAX spends tracing, lowering and compiling from now on (its monitoring
    events), summed into the returned dict's "seconds"."""
    spent = {"seconds": 0.0}

    def listen(event, duration, **_):
        if event in _COMPILE_EVENTS:
            spent["seconds"] += duration
    jax.monitoring.register_event_duration_secs_listener(listen)
    return spent


def _child(spec: dict) -> dict:
    """Run one fit in this (fresh) process; returns its figures."""
    t_import = time.perf_counter()
    compiling = _count_compilation()
    if spec.get("compile_cache"):       # the command line's on-disk cache, in this folder
        from ude_fit.cli.compile_cache import ENV, use_compile_cache
        use_compile_cache({ENV: spec["compile_cache"]})
    from ude_fit import FitOptions, TrainConfig, fit, load
    from ude_fit.analysis.continuation import trace_flutter
    ds = load([spec["data"]], "flutter")
    cfg = TrainConfig(**spec.get("train", {}))
    opts = FitOptions("flutter", approximator=spec["approximator"], training=spec["training"],
                      starts=spec["starts"], starts_together=spec.get("together", False),
                      seed=spec.get("seed", 0), train=cfg,
                      mechanistic=spec.get("mechanistic", "periodic"))
    first_ok = {}
    t0 = time.perf_counter()

    def progress(event, **kw):
        if event == "start_done" and "t" not in first_ok:
            m = kw["record"].metrics
            if m is not None and m.summary.branch_rms is not None \
                    and m.summary.branch_rms <= 0.01 and m.summary.missed == 0:
                first_ok["t"] = time.perf_counter() - t0
                first_ok["start"] = kw["record"].start

    res = fit(ds, opts, reference=spec["truth"], progress=progress)
    doc = res.to_json()
    total = time.perf_counter() - t0
    out = {"seconds_total": total, "seconds_import": t0 - t_import,
           "seconds_to_first_1pct": first_ok.get("t"), "first_1pct_start": first_ok.get("start"),
           "orbits": len(ds),
           "adequate": doc["starts"]["adequate"], "starts": opts.starts,
           "seconds_compiling": compiling["seconds"],
           # CPU time of the process: on a shared, loaded machine the honest figure beside
           # the wall time (on an idle 2-core machine wall >= cpu / 2)
           "cpu_seconds": sum(resource.getrusage(resource.RUSAGE_SELF)[:2]),
           "seconds_training": doc["starts"]["train_seconds"],
           "per_start": [{"start": r["start"], "status": r["status"], "loss": r.get("loss"),
                          "branch_rms": (r.get("metrics") or {}).get("branch_rms"),
                          "missed": (r.get("metrics") or {}).get("missed"),
                          "adequate": r["adequate"],
                          "seconds_diagram": (r["seconds"] - r["train_seconds"]
                                              if r.get("train_seconds") is not None else None)}
                         for r in doc["starts"]["records"]]}
    for side in ("mechanistic", "ude"):
        m = doc[side] or {}
        out[side] = {"branch_rms": m.get("branch_rms"), "branch_max": m.get("branch_max"),
                     "missed": m.get("missed"), "trajectory_rms": m.get("trajectory_rms"),
                     "hopf": (m.get("hopf") or {}).get("model"),
                     "hopf_error": (m.get("hopf") or {}).get("error"),
                     "fold": (m.get("fold") or {}).get("model"),
                     "fold_error": (m.get("fold") or {}).get("error")}
    if spec.get("time_continuation") and res.ude is not None:
        times = []
        for _ in range(3):
            t1 = time.perf_counter()
            br = trace_flutter(res.ude, v_range=res.ranges["v_range"],
                               amp_max=res.ranges["amp_max"], scales=res.scales)
            times.append(time.perf_counter() - t1)
        out["continuation"] = {"seconds_median": statistics.median(times),
                               "seconds_runs": times, "points": int(br.param.size)}
    return out


def _run_child(spec: dict) -> dict:
    r = subprocess.run([sys.executable, __file__, "--child", json.dumps(spec)],
                       capture_output=True, text=True, cwd=ROOT)
    if r.returncode != 0:
        return {"error": (r.stderr.strip().splitlines() or ["failed"])[-1]}
    return json.loads(r.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer starts and noise levels")
    ap.add_argument("--repeat", type=int, default=1, help="repeats of the timed fit (median)")
    ap.add_argument("--starts", type=int, default=16,
                    help="starts of the ensemble figure (default 16)")
    ap.add_argument("--only", choices=("ensemble", "step", "cache"),
                    help="only this figure (and the data it needs)")
    ap.add_argument("--out", help="also write the JSON here")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        print(json.dumps(_child(json.loads(a.child))))
        return 0

    from tests.ude_fixtures import flutter_branch, write_truth_campaign
    br = flutter_branch()
    truth = {"hopf": float(br.hopf[0]), "fold": float(min(f["V"] for f in br.folds))}
    tmp = tempfile.mkdtemp(prefix="ude_bench_")
    files = {}
    sigmas = (0.0,) if a.only else (0.0, 0.02) if a.quick else (0.0, 0.02, 0.04)
    for sigma in sigmas:
        for name, speeds in (("10", AIRSPEEDS_10), ("16", AIRSPEEDS_16)):
            if name == "10" or name == "16" and sigma == 0.0 and not a.only:
                path = os.path.join(tmp, f"flutter_{name}_s{sigma:g}.h5")
                write_truth_campaign(path, "flutter", airspeeds=speeds, sigma=sigma, seed=1)
                files[(name, sigma)] = path
    starts = 2 if a.quick else 5
    result = {"benchmark": "ude_fit", "truth": truth, "python": platform.python_version(),
              "machine": platform.machine(), "cpus": os.cpu_count()}

    if a.only == "step":
        result["periodic_step"] = _periodic_step(files[("10", 0.0)])
        print(json.dumps(result, indent=2))
        return 0
    if a.only == "cache":
        result["compile_cache"] = _compile_cache(files[("10", 0.0)], truth)
        print(json.dumps(result, indent=2))
        return 0
    if a.only != "ensemble":
        _single_and_comparisons(a, files, truth, starts, result)
        result["periodic_step"] = _periodic_step(files[("10", 0.0)])
    # many starts as one vectorised ensemble: 16 starts of the same fit, compile included
    # 16 starts of the same fit, compile included, trained together (--starts-together)
    # and one after another: the ratio is taken within this run
    for name, together in (("ensemble", True), ("one_after_another", False)):
        # no constraint rounds either way: the starts trained together cannot take them,
        # and the comparison is of the same training
        many = _run_child({"data": files[("10", 0.0)], "approximator": "nn",
                           "training": "periodic", "starts": a.starts, "truth": truth,
                           "together": together, "train": {"constraint_rounds": 0}})
        result[name] = {"starts": a.starts, "goal_seconds": 60,
                        "reached_1pct": sum(1 for r in many.get("per_start", [])
                                            if r["branch_rms"] is not None
                                            and r["branch_rms"] <= 0.01 and r["missed"] == 0),
                        **many}
    result["ensemble"]["training_speedup"] = (
        result["one_after_another"].get("seconds_training", float("nan"))
        / result["ensemble"].get("seconds_training", float("nan")))
    text = json.dumps(result, indent=2)
    print(text)
    if a.out:
        with open(a.out, "w") as fh:
            fh.write(text + "\n")
    return 0


def _compile_cache(path: str, truth: dict) -> dict:
    """The same one-start fit (the defaults) in two fresh processes sharing an empty
    on-disk compile cache (ude_fit/cli/compile_cache.py): cold, then warm."""
    folder = tempfile.mkdtemp(prefix="ude_bench_xla_")
    runs = [_run_child({"data": path, "approximator": "nn", "training": "periodic",
                        "starts": 1, "truth": truth, "mechanistic": "equation",
                        "compile_cache": folder}) for _ in range(2)]
    keys = ("seconds_total", "seconds_compiling", "cpu_seconds")
    return {"cold": {k: runs[0].get(k) for k in keys}, "warm": {k: runs[1].get(k) for k in keys},
            "wall_ratio_warm_to_cold": runs[1]["seconds_total"] / runs[0]["seconds_total"],
            "same_result": runs[0]["ude"] == runs[1]["ude"], "ude": runs[1]["ude"]}


def _median_ms(step, args, repeats: int) -> float:
    """Milliseconds of ``step(*args)``, median of ``repeats`` after one call to compile."""
    jax.block_until_ready(step(*args))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(step(*args))
        times.append(time.perf_counter() - t0)
    return round(1000 * statistics.median(times), 2)


def _periodic_step(path: str, repeats: int = 20) -> dict:
    """Milliseconds of one periodic training step (value and gradient, the default 2x12
    network, median of ``repeats`` after compiling), the plain network against the rest-free
    one, on the same orbits, initial weights and mechanistic model; and the rest-free one's
    step with the orbits collocated instead of shot."""
    import equinox as eqx
    import jax.numpy as jnp
    from ude_fit import load
    from ude_fit.fitting import prepare
    from ude_fit.mechanistic_stage import identify_mechanistic
    from ude_fit.models.ude import UDE
    from ude_fit.training.collocation import collocation_loss, collocation_unknowns
    from ude_fit.training.losses import periodic_loss
    from ude_fit.training.options import TrainConfig
    from ude_fit.training.train import _trainable_spec, new_correction
    _, data, *_ = prepare(load([path], "flutter"), "flutter", None, 32)
    mech, _ = identify_mechanistic(data, "flutter")
    out = {"orbits": int(data.n_orbits), "repeats": repeats}
    for name, rest_free in (("plain", False), ("rest_free", True)):
        cfg = TrainConfig(rest_free=rest_free).for_system("flutter")
        corr = new_correction(UDE(mech), data, jax.random.PRNGKey(0), cfg)
        trained, static = eqx.partition(corr, _trainable_spec(corr))
        params = {"corr": trained, "dy0": jnp.zeros(data.ys[:, 0, :].shape),
                  "dT": jnp.zeros(data.period.shape)}
        step = eqx.filter_jit(jax.value_and_grad(periodic_loss))
        out[f"{name}_ms"] = _median_ms(step, (params, static, mech, data, cfg, None), repeats)
    out["ratio"] = round(out["rest_free_ms"] / out["plain_ms"], 3)
    # the rest-free step at fewer RK4 steps between samples (the default is the system's):
    # the step's cost is about linear in them; what they cost in accuracy is in
    # docs/experiments.md (thirty-fifth session)
    for substeps in (1, 2):
        cfg = TrainConfig(substeps=substeps).for_system("flutter")
        out[f"rest_free_substeps_{substeps}_ms"] = _median_ms(
            step, (params, static, mech, data, cfg, None), repeats)
    out["default_substeps"] = TrainConfig().for_system("flutter").substeps
    # the collocated step with free series (the default plan's first leg), the same orbits,
    # weights and model
    cfg = TrainConfig(collocation_series="free").for_system("flutter")
    cparams = {"corr": params["corr"], **collocation_unknowns(data, mech.autonomous)}
    out["collocation_ms"] = _median_ms(eqx.filter_jit(jax.value_and_grad(collocation_loss)),
                                       (cparams, static, mech, data, cfg, None), repeats)
    out["shooting_over_collocation"] = round(out["rest_free_ms"] / out["collocation_ms"], 2)
    # and with every orbit's series solved for the model (the default plan's second leg)
    solved = TrainConfig(collocation_series="solved").for_system("flutter")
    sparams = {"corr": params["corr"],
               **collocation_unknowns(data, mech.autonomous, series="solved")}
    out["collocation_solved_ms"] = _median_ms(
        eqx.filter_jit(jax.value_and_grad(collocation_loss)),
        (sparams, static, mech, data, solved, None), repeats)
    out["solved_over_free"] = round(out["collocation_solved_ms"] / out["collocation_ms"], 2)
    return out


def _single_and_comparisons(a, files, truth, starts, result) -> None:
    # 1. wall time to fit the 2x12 UDE on 10 orbits to 1 % branch error, compile included
    runs = [_run_child({"data": files[("10", 0.0)], "approximator": "nn",
                        "training": "periodic", "starts": 1, "truth": truth,
                        "time_continuation": True}) for _ in range(max(1, a.repeat))]
    ok = [r for r in runs if "error" not in r]
    result["fit_to_1pct"] = {
        "orbits": ok[0]["orbits"] if ok else None,
        "seconds_median": statistics.median(r["seconds_total"] for r in ok) if ok else None,
        "reached_1pct": [r["ude"]["branch_rms"] is not None and r["ude"]["branch_rms"] <= 0.01
                         for r in ok],
        "ude_branch_rms": [r["ude"]["branch_rms"] for r in ok],
        "mechanistic_branch_rms": ok[0]["mechanistic"]["branch_rms"] if ok else None,
        "goal_seconds": 60, "runs": runs}
    result["continuation_per_branch"] = ok[0].get("continuation") if ok else None

    # 2. periodic-orbit against trajectory training, same data, same starts
    comp = {}
    for training in ("periodic", "trajectory"):
        comp[training] = _run_child({"data": files[("10", 0.0)], "approximator": "nn",
                                     "training": training, "starts": starts, "truth": truth})
    result["periodic_vs_trajectory"] = comp

    # 3. noise: NN and GP at each sigma
    noise = []
    for (name, sigma), path in sorted(files.items()):
        if name != "10":
            continue
        for approx in ("nn", "gp"):
            r = _run_child({"data": path, "approximator": approx, "training": "periodic",
                            "starts": 1 if approx == "gp" else min(starts, 3), "truth": truth})
            noise.append({"sigma": sigma, "approximator": approx, **r})
    result["noise"] = noise


if __name__ == "__main__":
    sys.exit(main())
