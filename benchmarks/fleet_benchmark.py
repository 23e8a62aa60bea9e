"""Fleets and sweeps on Ray: throughput with one and two local nodes, Ray's overhead per task,
and a sweep against its fits run one after another. Prints one JSON object.

    python3 benchmarks/fleet_benchmark.py [--members 4] [--fits 2]

Everything runs on a real local Ray cluster (tests/ray_cluster.py: `ray start` node processes,
one CPU each) inside a network namespace that holds only loopback: the script re-runs itself
under `unshare -n` (root needed). Figures are for this machine; docs/cluster.md scales them.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
# the sequential fits run the command line, whose on-disk cache of compiled code the sweep's
# workers do not use: off here, so both sides compile (ude_fit/cli/compile_cache.py)
os.environ["UDE_FIT_COMPILE_CACHE"] = ""


def _fleet_file(work: Path, name: str, seeds: list[int]) -> Path:
    from tests.cluster_scenario import FLUTTER     # the cluster tests' small campaign
    (work / "bench.toml").write_text(FLUTTER.format(name="bench", values="[20.5]"))
    f = work / f"{name}.toml"
    f.write_text(f'[fleet]\nname = "{name}"\ncampaigns = ["bench.toml"]\nseeds = {seeds}\n'
                 'clock = "lockstep"\n')
    return f


def _run_fleet(work: Path, name: str, seeds: list[int], address: str) -> float:
    from cbc_controller.fleet import load_fleet, run_fleet
    options = load_fleet(_fleet_file(work, name, seeds))
    t0 = time.perf_counter()
    status = run_fleet(options, work / name, address, stream=io.StringIO())
    wall = time.perf_counter() - t0
    if status != 0:
        raise RuntimeError(f"fleet {name} ended with status {status}")
    return wall


def _noop_overhead(n: int = 50) -> dict:
    import ray

    @ray.remote(num_cpus=1)
    def noop():
        return None

    ray.get(noop.remote())                          # a warm worker
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        ray.get(noop.remote())
        times.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    ray.get([noop.remote() for _ in range(200)])
    batch = time.perf_counter() - t0
    return {"noop_round_trip_ms_median": round(1e3 * statistics.median(times), 2),
            "noop_round_trip_ms_p90": round(1e3 * sorted(times)[int(0.9 * n)], 2),
            "noop_tasks_per_s_batch_of_200": round(200 / batch, 1)}


def _member_alone(work: Path) -> float:
    from cbc_controller.fleet import load_fleet, run_member
    member = load_fleet(_fleet_file(work, "alone", [99])).members()[0]
    t0 = time.perf_counter()
    result = run_member(member)
    assert result.status == "completed", result
    return time.perf_counter() - t0


def _sweep(work: Path, n_fits: int, address: str) -> dict:
    from tests.ude_fixtures import write_truth_campaign
    from ude_fit.sweep import load_sweep, run_sweep
    data = work / "truth_osc.h5"
    write_truth_campaign(data, "oscillator", per_freq=2)
    seeds = list(range(n_fits))
    (work / "sweep.toml").write_text(f'[sweep]\nsystem = "oscillator"\ndatasets = '
                                     f'["truth_osc.h5"]\nseeds = {seeds}\n[[options]]\n'
                                     'label = "one"\nstarts = 1\n')
    t0 = time.perf_counter()
    status = run_sweep(load_sweep(work / "sweep.toml"), work / "S", address, stream=io.StringIO())
    on_ray = time.perf_counter() - t0
    if status != 0:
        raise RuntimeError(f"sweep ended with status {status}")
    t0 = time.perf_counter()
    for seed in seeds:
        subprocess.run([sys.executable, "-m", "ude_fit.cli", "fit", str(data), "--system",
                        "oscillator", "--seed", str(seed), "--starts", "1", "--out",
                        str(work / f"seq{seed}"), "--quiet"], check=True, capture_output=True)
    sequential = time.perf_counter() - t0
    return {"fits": n_fits, "sweep_wall_s_two_nodes": round(on_ray, 1),
            "fits_one_after_another_s": round(sequential, 1),
            "speedup": round(sequential / on_ray, 2)}


def measure(members: int, fits: int) -> dict:
    from tests.ray_cluster import LocalRayCluster
    out: dict = {"machine_cores": os.cpu_count(), "load_average_at_start": os.getloadavg()[0],
                 "members_per_fleet": members, "member": "flutter, 1 airspeed (2 points), lockstep (tests/cluster_scenario.py FLUTTER)"}
    work = Path(tempfile.mkdtemp(prefix="fleet-bench-"))
    with LocalRayCluster() as cluster:
        os.environ.update(cluster.env)
        cluster.start_head(num_cpus=1)
        import ray
        ray.init(address=cluster.address, log_to_driver=False)
        out["ray_overhead"] = _noop_overhead()
        alone = _member_alone(work)
        inside = _run_fleet(work, "single", [98], cluster.address)
        out["member_wall_s_alone"] = round(alone, 2)
        out["member_wall_s_as_a_one_member_fleet"] = round(inside, 2)
        out["ray_overhead_per_member_s"] = round(inside - alone, 2)
        one = _run_fleet(work, "one_node", list(range(members)), cluster.address)
        cluster.add_node(num_cpus=1)
        two = _run_fleet(work, "two_nodes", list(range(100, 100 + members)), cluster.address)
        out["fleet_one_node"] = {"wall_s": round(one, 1),
                                 "campaigns_per_min": round(60 * members / one, 2)}
        out["fleet_two_nodes"] = {"wall_s": round(two, 1),
                                  "campaigns_per_min": round(60 * members / two, 2)}
        out["two_node_speedup"] = round(one / two, 2)
        out["sweep"] = _sweep(work, fits, cluster.address)
        ray.shutdown()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--members", type=int, default=4, help="members per fleet (default 4)")
    ap.add_argument("--fits", type=int, default=2, help="fits in the sweep (default 2)")
    args = ap.parse_args()
    if os.environ.get("FLEET_BENCH_IN_NAMESPACE") != "1":
        from tests.ray_cluster import loopback_namespace_command, namespace_unavailable
        why = namespace_unavailable()
        if why:
            sys.exit(f"fleet_benchmark: {why}")
        env = {**os.environ, "FLEET_BENCH_IN_NAMESPACE": "1"}
        sys.exit(subprocess.run(loopback_namespace_command(
            [sys.executable, *sys.argv]), env=env).returncode)
    print(json.dumps(measure(args.members, args.fits), indent=1))


if __name__ == "__main__":
    main()
