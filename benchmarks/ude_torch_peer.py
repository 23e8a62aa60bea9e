"""UDE fit benchmark against a PyTorch + torchdiffeq peer: prints one JSON object.

The issue's figure: wall time to fit the aerofoil UDE (2x12 sigmoid MLP correction on the
quasi-steady model) to the noise-free truth orbits at 18, 19.5, 21, 22.5 and 23.6 m/s
(10 orbits, stable and unstable), ude_fit's JAX training against the same fit written with
PyTorch and torchdiffeq, reported as the ratio torch / jax.

Both sides do the same work:
* the correction's scaling from the residual forces the identified mechanistic model
  leaves on the 32 samples per orbit;
* equation-error warm start: Adam (lr 1e-2) 1500 steps, then L-BFGS 100 iterations;
* trajectory loss: one period from each measured initial state, fixed-step RK4 with 4
  steps per sample (T / 128), states at the 32 sample phases against the data, mean
  squared error scaled by the data's RMS state: Adam (lr 3e-3) 300 steps, then L-BFGS
  100 iterations.
The torch side integrates all orbits in one batch in normalised time s = t / T (the field
times T, step 1/128), torchdiffeq.odeint(method="rk4", step_size=1/128), which is the same
per-orbit step; torchdiffeq's "rk4" is the 3/8-rule variant, ude_fit's the classical one.

Not timed for either side: imports, writing the campaign, loading it, sampling it and the
mechanistic identification (equation-error least squares; shared, the same numbers on both
sides). fit_seconds is the training call alone, compilation included on the JAX side: it
runs first, in a fresh subprocess, before anything in that process has compiled a
training function. Both fitted models are then judged by the same yardstick, ude_fit's own
continuation and branch metrics (the torch weights copied into an ude_fit MLPCorrection),
timed separately as eval_seconds.

Usage: python benchmarks/ude_torch_peer.py
If torch or torchdiffeq cannot be imported it prints a record saying so and exits 0.
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax  # noqa: E402  (after the imports above, before any array)

jax.config.update("jax_enable_x64", True)       # ude_fit computes in float64 (see ude_fit docs)

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

AIRSPEEDS = (18, 19.5, 21, 22.5, 23.6)
SAMPLES = 32
THREADS = 2
SEED = 0


# ---------------------------------------------------------------------------------------
# shared preparation (not timed)
# ---------------------------------------------------------------------------------------

def prepare(path):
    """Dataset, training arrays, identified mechanistic model and the diagram ranges."""
    from ude_fit.data.load import load
    from ude_fit.analysis.diagram import diagram_ranges
    from ude_fit.training.identify import identify, training_data

    ds = load([path], "flutter")
    data = training_data(ds, n=SAMPLES)
    t0 = time.perf_counter()
    mech, ident = identify(data, "flutter")
    return ds, data, mech, ident, diagram_ranges(ds), time.perf_counter() - t0


def evaluate(model, ds, data, ranges) -> dict:
    """ude_fit's yardstick: traced diagram, then branch errors at every measured orbit."""
    import numpy as np

    from ude_fit.analysis.diagram import trace_diagram
    from ude_fit.analysis.metrics import branch_metrics, locations

    scales = np.asarray(data.y_scale)
    t0 = time.perf_counter()
    diagram = trace_diagram(model, ranges, scales)
    m = branch_metrics(model, diagram, ds, scales=scales).summary.to_json()
    loc = locations(diagram)
    return {"branch_rms": m["branch_rms"], "branch_max": m["branch_max"], "missed": m["missed"],
            "trajectory_rms": m["trajectory_rms"], "hopf": loc["hopf"], "fold": loc["fold"],
            "reached_1pct": bool(m["branch_rms"] is not None and m["missed"] == 0
                                 and m["branch_rms"] <= 0.01),
            "eval_seconds": time.perf_counter() - t0}


# ---------------------------------------------------------------------------------------
# the JAX side: ude_fit's own training, in a fresh subprocess
# ---------------------------------------------------------------------------------------

def jax_worker(path: str) -> None:
    import jax

    from ude_fit.models.ude import UDE
    from ude_fit.training.options import TrainConfig
    from ude_fit.training.train import train_ude

    ds, data, mech, _, ranges, _ = prepare(path)
    t0 = time.perf_counter()
    model, info = train_ude(UDE(mech), data, key=jax.random.PRNGKey(SEED), cfg=TrainConfig(),
                            training="trajectory")
    jax.block_until_ready(model)
    fit_s = time.perf_counter() - t0
    out = {"fit_seconds": fit_s, "final_loss": float(info["final_loss"]),
           "equation_loss": float(info["equation_loss"])}
    out.update(evaluate(model, ds, data, ranges))
    print(json.dumps(out))


def run_jax_side(path: str) -> dict:
    r = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--jax-worker", path],
                       capture_output=True, text=True, cwd=REPO)
    if r.returncode != 0:
        return {"error": r.stderr.strip().splitlines()[-1] if r.stderr.strip() else
                f"exit {r.returncode}"}
    return json.loads(r.stdout.strip().splitlines()[-1])


# ---------------------------------------------------------------------------------------
# the torch peer
# ---------------------------------------------------------------------------------------

def torch_fit(data, mech_params: dict, *, width=12, depth=2, equation_steps=1500,
              adam_steps=300, lbfgs_steps=100, lr=3e-3, substeps=4, init_scale=1e-2):
    """The same UDE and the same two-stage training in PyTorch (float64).

    Returns (mlp, scaling dict of numpy arrays, info)."""
    import numpy as np
    import torch
    from torch import nn
    from torchdiffeq import odeint

    dt = torch.float64
    p = {k: torch.tensor(float(v), dtype=dt) for k, v in mech_params.items()}
    ys = torch.tensor(np.array(data.ys), dtype=dt)             # (n_o, n, 4)
    qdd = torch.tensor(np.array(data.qdd), dtype=dt)           # (n_o, n, 2)
    T = torch.tensor(np.array(data.period), dtype=dt)          # (n_o,)
    V = torch.tensor(np.array(data.drive.param), dtype=dt)     # (n_o,)
    y_scale = torch.tensor(np.array(data.y_scale), dtype=dt)   # (4,)
    n_o, n, ns = ys.shape
    pi = torch.pi

    # --- FlutterQS: mass, aero damping and stiffness, force --------------------------
    b, a, rho = p["b"], p["a"], p["rho"]
    m12 = p["m_w"] * p["x_alpha"] * b - rho * pi * b ** 3 * a
    M = torch.stack([torch.stack([p["m_T"] + rho * pi * b ** 2, m12]),
                     torch.stack([m12, p["I_alpha"] + rho * pi * b ** 4 * (0.125 + a ** 2)])])

    def aero(Vb):
        """Aero damping and stiffness, (B, 2, 2) each, for airspeeds Vb (B,)."""
        z = torch.zeros_like(Vb)
        B = torch.stack([torch.stack([2 * pi * rho * b * Vb, 2 * pi * rho * b ** 2 * Vb * (1 - a)], -1),
                         torch.stack([-2 * pi * rho * b ** 2 * Vb * (a + 0.5),
                                      -2 * a * rho * b ** 3 * Vb * pi * (0.5 - a)], -1)], -2)
        S = torch.stack([torch.stack([z, 2 * pi * rho * b * Vb ** 2], -1),
                         torch.stack([z, -2 * pi * rho * b ** 2 * Vb ** 2 * (0.5 + a)], -1)], -2)
        return B, S

    def force(q, qd, B, S):
        """-(struct + B q' + S q + f_NL), batched: q, qd (B, 2), B, S (B, 2, 2)."""
        h, al = q[:, 0], q[:, 1]
        struct = torch.stack([p["c_h"] * qd[:, 0] + p["k_h"] * h,
                              p["c_alpha"] * qd[:, 1] + p["k_alpha"] * al
                              + p["k_alpha2"] * al ** 2 + p["k_alpha3"] * al ** 3], -1)
        return -(struct + (B @ qd[:, :, None])[:, :, 0] + (S @ q[:, :, None])[:, :, 0])

    t_start = time.perf_counter()
    # --- residual forces and the correction's scaling (ude_fit.feature_scaling) ------
    Vs = V[:, None].expand(n_o, n).reshape(-1)
    yf = ys.reshape(-1, ns)
    Bs, Ss = aero(Vs)
    R = (qdd.reshape(-1, 2) @ M.T) - force(yf[:, :2], yf[:, 2:], Bs, Ss)
    Z = torch.cat([yf, Vs[:, None]], 1)
    z_mean = Z.mean(0)
    z_scale = Z.std(0, correction=0)
    z_scale = torch.where(z_scale > 1e-12 * (1 + z_mean.abs()), z_scale, torch.ones_like(z_scale))
    out_scale = torch.sqrt(torch.mean(R ** 2, 0))
    out_scale = torch.where(out_scale > 0, out_scale, torch.ones_like(out_scale))

    # --- MLP: 5 -> 12 -> 12 -> 2, sigmoid, last layer shrunk --------------------------
    layers, n_in = [], Z.shape[1]
    for _ in range(depth):
        layers += [nn.Linear(n_in, width, dtype=dt), nn.Sigmoid()]
        n_in = width
    layers.append(nn.Linear(n_in, 2, dtype=dt))
    mlp = nn.Sequential(*layers)
    with torch.no_grad():
        mlp[-1].weight.mul_(init_scale)
        mlp[-1].bias.mul_(init_scale)

    def correction(z):
        return out_scale * mlp((z - z_mean) / z_scale)

    # --- the UDE over all orbits at once, in normalised time s = t / T ----------------
    # M q'' = -(K + S(V)) q - (C + B(V)) q' - (0, k_a2 a^2 + k_a3 a^3) + U: the airspeed
    # is fixed per orbit, so the linear part is one (4, 2) matrix per orbit, computed once,
    # with M^-1 and T folded in.
    Minv = torch.linalg.inv(M)
    B_o, S_o = aero(V)
    Ks = torch.diag(torch.stack([p["k_h"], p["k_alpha"]]))
    Cs = torch.diag(torch.stack([p["c_h"], p["c_alpha"]]))
    lin = -torch.cat([(Ks + S_o).transpose(1, 2), (Cs + B_o).transpose(1, 2)], 1)  # (n_o, 4, 2)
    lin_acc = T[:, None, None] * (lin @ Minv.T)                                    # y -> T q''
    MinvT_T = T[:, None, None] * Minv.T                                            # U -> T q''
    nl_T = T[:, None] * Minv[:, 1]                   # T q'' per unit of (k_a2 a^2 + k_a3 a^3)
    Vcol = V[:, None]

    def field(s, y):
        al = y[:, 1:2]
        U = correction(torch.cat([y, Vcol], 1))
        acc = ((y[:, None, :] @ lin_acc) + (U[:, None, :] @ MinvT_T))[:, 0]
        acc = acc - (p["k_alpha2"] * al ** 2 + p["k_alpha3"] * al ** 3) * nl_T
        return torch.cat([T[:, None] * y[:, 2:], acc], 1)

    s_samples = torch.arange(n, dtype=dt) / n
    step = 1.0 / (n * substeps)

    def equation_loss():
        return torch.mean(((correction(Z) - R) / out_scale) ** 2)

    def trajectory_loss():
        sim = odeint(field, ys[:, 0, :], s_samples, method="rk4",
                     options={"step_size": step})                    # (n, n_o, 4)
        return torch.mean(((sim.transpose(0, 1) - ys) / y_scale) ** 2)

    def minimize(loss_fn, steps, lr_, stage):
        """Adam for ``steps`` steps, then L-BFGS (strong Wolfe) for ``lbfgs_steps``
        iterations, with no early stop on tolerances (as many steps as the JAX side)."""
        out = {}
        opt = torch.optim.Adam(mlp.parameters(), lr=lr_)
        for k in range(steps):
            opt.zero_grad()
            val = loss_fn()
            val.backward()
            opt.step()
            if not torch.isfinite(val):
                raise FloatingPointError(f"{stage}: loss is not finite at Adam step {k + 1}")
            out["adam_loss"] = float(val.detach())
        if lbfgs_steps > 0:
            saved = [w.detach().clone() for w in mlp.parameters()]
            opt = torch.optim.LBFGS(mlp.parameters(), lr=1.0, max_iter=lbfgs_steps,
                                    max_eval=lbfgs_steps * 25, history_size=10,
                                    tolerance_grad=0.0, tolerance_change=0.0,
                                    line_search_fn="strong_wolfe")

            def closure():
                opt.zero_grad()
                v = loss_fn()
                v.backward()
                return v

            opt.step(closure)
            st = opt.state[opt.param_groups[0]["params"][0]]
            out["lbfgs_iterations"] = int(st.get("n_iter", 0))
            out["lbfgs_evaluations"] = int(st.get("func_evals", 0))
        with torch.no_grad():
            val = float(loss_fn())
        if lbfgs_steps > 0 and not np.isfinite(val):
            with torch.no_grad():
                for w, w0 in zip(mlp.parameters(), saved):
                    w.copy_(w0)
                val = float(loss_fn())
            out["lbfgs_reverted"] = True
        if not np.isfinite(val):
            raise FloatingPointError(f"{stage}: loss is not finite")
        out["loss"] = val
        return out

    info = {}
    eq = minimize(equation_loss, equation_steps, 1e-2, "equation")
    info["equation_loss"] = eq.pop("loss")
    info["equation"] = eq
    tr = minimize(trajectory_loss, adam_steps, lr, "trajectory")
    info["final_loss"] = tr.pop("loss")
    info["trajectory"] = tr
    info["fit_seconds"] = time.perf_counter() - t_start
    scaling = {"z_mean": z_mean.numpy(), "z_scale": z_scale.numpy(),
               "out_scale": out_scale.numpy()}
    vf = lambda y: field(0.0, y) / T[:, None]          # the unscaled field, for the port check
    return mlp, scaling, info, vf


def to_ude(mech, mlp, scaling: dict):
    """The torch MLP as an ude_fit MLPCorrection (eqx.nn.Linear: weight (out, in), bias (out,))."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from ude_fit.models.corrections import MLPCorrection, Scaling
    from ude_fit.models.ude import UDE

    lin = [m for m in mlp if hasattr(m, "weight")]
    sc = Scaling(*(jnp.asarray(scaling[k]) for k in ("z_mean", "z_scale", "out_scale")))
    corr = MLPCorrection(lin[0].in_features, lin[-1].out_features, sc, width=lin[0].out_features,
                         depth=len(lin) - 1, key=jax.random.PRNGKey(SEED))
    n = len(corr.mlp.layers)
    assert n == len(lin)
    corr = eqx.tree_at(
        lambda c: [c.mlp.layers[i].weight for i in range(n)] + [c.mlp.layers[i].bias
                                                                for i in range(n)],
        corr, [jnp.asarray(m.weight.detach().numpy()) for m in lin]
        + [jnp.asarray(m.bias.detach().numpy()) for m in lin])
    return UDE(mech, corr)


def port_check(model, vf, data) -> float:
    """Largest relative difference between the torch field and ude_fit's on the data."""
    import jax
    import numpy as np
    import torch

    ys = np.asarray(data.ys)[:, ::4]                       # (n_o, 8, 4)
    drive = data.drive
    worst = 0.0
    for j in range(ys.shape[1]):
        y = ys[:, j]
        with torch.no_grad():
            ft = vf(torch.tensor(np.array(y))).numpy()
        fj = np.asarray(jax.vmap(lambda yy, d: model.vector_field(0.0, yy, d))(y, drive))
        worst = max(worst, float(np.max(np.abs(ft - fj) / (np.abs(fj) + 1e-12))))
    return worst


def versions() -> dict:
    from importlib.metadata import PackageNotFoundError, version
    out = {"python": platform.python_version()}
    for pkg in ("jax", "jaxlib", "equinox", "optax", "numpy", "torch", "torchdiffeq"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = None
    return out


def main() -> None:
    record = {"benchmark": "ude_torch_peer"}
    load_before = os.getloadavg()
    try:
        import torch
        import torchdiffeq  # noqa: F401
    except Exception as exc:                                   # noqa: BLE001
        record.update(available=False, reason=f"peer unavailable: {type(exc).__name__}: {exc}",
                      versions=versions())
        print(json.dumps(record))
        return

    tmp = tempfile.mkdtemp(prefix="ude_torch_peer_")
    try:
        record.update(run(os.path.join(tmp, "flutter_truth.h5"), torch))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    record["load_average_1min"] = {"start": load_before[0], "end": os.getloadavg()[0]}
    print(json.dumps(record))


def run(path: str, torch) -> dict:
    from ude_fixtures import write_truth_campaign

    t0 = time.perf_counter()
    write_truth_campaign(path, "flutter", airspeeds=AIRSPEEDS)
    data_s = time.perf_counter() - t0

    # JAX first, alone, in a fresh process: nothing compiled before its fit
    jax_side = run_jax_side(path)

    torch.set_num_threads(THREADS)
    torch.manual_seed(SEED)
    ds, data, mech, ident, ranges, ident_s = prepare(path)
    from ude_fit.models.mechanistic import parameters_of
    try:
        mlp, scaling, info, vf = torch_fit(data, parameters_of(mech))
        model = to_ude(mech, mlp, scaling)
        torch_side = {"fit_seconds": info["fit_seconds"], "final_loss": info["final_loss"],
                      "equation_loss": info["equation_loss"],
                      "lbfgs": {"equation": info["equation"], "trajectory": info["trajectory"]},
                      "port_check_max_rel_diff": port_check(model, vf, data)}
        torch_side.update(evaluate(model, ds, data, ranges))
    except FloatingPointError as exc:
        torch_side = {"error": str(exc)}

    ratio = None
    if "fit_seconds" in jax_side and "fit_seconds" in torch_side:
        ratio = torch_side["fit_seconds"] / jax_side["fit_seconds"]
    return {
        "available": True,
        "orbits": len(ds),
        "stable": int(sum(bool(o.stable) for o in ds.orbits)),
        "airspeeds": list(AIRSPEEDS),
        "jax": jax_side,
        "torch": torch_side,
        "ratio_torch_over_jax": ratio,
        "goal_jax_fit_seconds": 60.0,
        "untimed": {"data_seconds": data_s, "identify_seconds": ident_s,
                    "note": "campaign writing, loading, sampling and identification are shared "
                            "and timed for neither side; eval_seconds is separate from fit"},
        "versions": versions(),
        "threads": {"torch": torch.get_num_threads(), "cpus": os.cpu_count()},
    }


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--jax-worker":
        jax_worker(sys.argv[2])
    else:
        main()
