"""The cluster tests' scenario, run once inside a loopback-only network namespace
(tests/test_cluster.py starts it under ``unshare -n``): a real two-node Ray cluster, a fleet
whose second node is killed mid-run, its rerun, an interrupted fleet and its rerun, and a fit
sweep. It writes what it saw to WORK/results.json; the tests judge it.

    unshare -n sh -c 'ip link set lo up && exec python3 tests/cluster_scenario.py WORK'
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.ray_cluster import LONG_AIRSPEEDS, LocalRayCluster  # noqa: E402

FLUTTER = """[campaign]
name = "{name}"
rig = "flutter"
seed = 1
[rig]
lockstep = true
[loop]
lockstep_slice_s = 0.2
[parameter]
values = {values}
[cbc]
kp = 200.0
kd = 60.0
navg = 4
transient_periods = 1
"""

OSCILLATOR = """[campaign]
name = "{name}"
rig = "oscillator"
seed = 1
[rig]
lockstep = true
[frequencies]
values = [{freq}]
[cbc]
kp = 1.0e4
kd = 50.0
"""

BURNT_PLUGIN = '''def force(t, q, qdot, params):
    raise RuntimeError("shaker coil burnt out")
'''

FLEET_A = """[fleet]
name = "lost-node"
campaigns = ["small.toml", "osc23.toml", "osc22.toml"]
seeds = [3]
clock = "lockstep"

[[settings]]
label = "clean"

[[settings]]
label = "cubic"            # undeclared physics: a hardening heave spring
rig = "flutter"
effects = { heave_cubic = 5e5 }

[[settings]]
label = "burnt"            # a rig that fails to start
rig = "flutter"
plugin = "burnt.py:force"
"""

FLEET_B = """[fleet]
name = "interrupted"
campaigns = ["one.toml", "four.toml"]
seeds = [5]
clock = "lockstep"
"""

SWEEP = """[sweep]
name = "approximators"
system = "oscillator"
datasets = ["truth_osc.h5"]
seeds = [0, 1]

[[options]]
label = "gp"
approximator = "gp"
starts = 1

[[options]]
label = "gp-periodic"
approximator = "gp"
mechanistic = "periodic"
starts = 1
"""


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class Driver:
    """A fleet or sweep command as a process, its stderr collected as it comes."""

    def __init__(self, args: list[str], env: dict):
        # SIGINT at its default in the child: a test run started in the background by a
        # non-interactive shell inherits it ignored, and the Ctrl-C test would then stop
        # nothing (two CI runs launched with `nohup ... &` failed so)
        self.proc = subprocess.Popen([sys.executable, "-m", *args], cwd=REPO, env=env,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     preexec_fn=_default_sigint)
        self.err = b""
        self._t = threading.Thread(target=self._pump, daemon=True)
        self._t.start()

    def _pump(self):
        while chunk := self.proc.stderr.read1(4096):
            self.err += chunk

    def wait_for(self, text: str, timeout: float = 400) -> None:
        t0 = time.time()
        while text.encode() not in self.err:
            if self.proc.poll() is not None or time.time() - t0 > timeout:
                raise RuntimeError(f"no {text!r}: {self.err.decode()[-3000:]}")
            time.sleep(0.1)

    def finish(self, timeout: float = 600) -> dict:
        rc = self.proc.wait(timeout=timeout)
        self._t.join(timeout=5)
        return {"rc": rc, "stderr": self.err.decode()}


def _wait_running(where, fragment: str, for_s: float, driver: Driver,
                  timeout: float = 300) -> int:
    """Until one process matching `fragment` has run on `where` (a node, or any node of a
    cluster) for `for_s` seconds, while `driver` runs; returns its pid."""
    t0, seen = time.time(), {}
    while time.time() - t0 < timeout and driver.proc.poll() is None:
        now = time.time()
        seen = {pid: seen.get(pid, now) for pid in where.running(fragment)}
        for pid, since in seen.items():
            if now - since >= for_s:
                return pid
        time.sleep(0.2)
    raise RuntimeError(f"no {fragment!r} ran: {driver.err.decode()[-3000:]}")


def _freeze_member(where, driver: Driver, for_s: float = 2.0) -> int:
    """A member's controller that has run on `where` for `for_s` seconds, stopped (SIGSTOP)
    so that it cannot finish between being chosen and its node being lost; its pid."""
    while True:
        pid = _wait_running(where, "cbc_controller.cli run", for_s, driver)
        try:
            os.kill(pid, signal.SIGSTOP)
            return pid
        except ProcessLookupError:     # it finished just now: take the next one
            continue


def _wait_points(member_folder: str, n: int, since: float, timeout: float = 300) -> None:
    """Until the campaign file a member is writing in its scratch folder (on this machine:
    the nodes are local) holds `n` points. Only folders made at or after ``since`` count:
    an earlier run's scratch folder left in the temporary directory (a run killed before it
    could clean up) would otherwise answer at once."""
    import glob
    import tempfile
    from cbc_controller.log import read_campaign
    pattern = os.path.join(tempfile.gettempdir(), member_folder + "-*", "campaign.h5")
    t0 = time.time()
    while time.time() - t0 < timeout:
        for path in glob.glob(pattern):
            try:
                if (os.stat(os.path.dirname(path)).st_mtime >= since
                        and len(read_campaign(path).points) >= n):
                    return
            except Exception:            # mid-commit or not created yet: look again
                pass
        time.sleep(0.2)
    raise RuntimeError(f"{member_folder} logged no {n} points")


def _member_of(pid: int) -> str:
    """The fleet member a controller process runs: its scratch folder is fleet-<id>-XXXXXXXX."""
    cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    return re.search(r"/fleet-(.+)-[a-z0-9_]{8}/campaign\.toml", cmd).group(1)


def _hashes(folder: Path) -> dict:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.glob("members/*/campaign.h5"))}


def _fleet(cfg: str, out: Path, env: dict) -> Driver:
    return Driver(["cbc_controller.cli", "fleet", cfg, "--out", str(out)], env)


def main(work: Path) -> None:
    work.mkdir(parents=True, exist_ok=True)
    (work / "small.toml").write_text(FLUTTER.format(name="small", values="[18.5, 20.5, 22.3]"))
    (work / "one.toml").write_text(FLUTTER.format(name="one", values="[20.5]"))
    # long enough (10 airspeeds, ~20 points) that a Ctrl-C after its second point finds it
    # still running on an idle machine (4 airspeeds finished before the stop reached it)
    (work / "four.toml").write_text(FLUTTER.format(name="four", values=str(list(LONG_AIRSPEEDS))))
    (work / "osc23.toml").write_text(OSCILLATOR.format(name="osc23", freq=23.0))
    (work / "osc22.toml").write_text(OSCILLATOR.format(name="osc22", freq=22.5))
    (work / "burnt.py").write_text(BURNT_PLUGIN)
    (work / "fleet_a.toml").write_text(FLEET_A)
    (work / "fleet_b.toml").write_text(FLEET_B)
    (work / "sweep.toml").write_text(SWEEP)
    from tests.ude_fixtures import write_truth_campaign
    write_truth_campaign(work / "truth_osc.h5", "oscillator", per_freq=2)

    res: dict = {}
    with LocalRayCluster() as cluster:
        head = cluster.start_head(num_cpus=1)
        second = cluster.add_node(num_cpus=1)
        res["nodes"] = {"head": head.node_id, "second": second.node_id}
        env = {**cluster.env, "RAY_ADDRESS": cluster.address}     # Ray's own convention

        # fleet A: the second node is lost while both nodes run members
        a = _fleet(str(work / "fleet_a.toml"), work / "A", env)
        # a member under way there, frozen so that it is still unfinished when the node goes
        res["lost_member"] = _member_of(_freeze_member(second, a))
        second.kill()
        res["killed_at"] = a.err.decode().count("\n[")
        third = cluster.add_node(num_cpus=1)
        res["nodes"]["third"] = third.node_id
        res["fleet_a"] = a.finish()
        res["fleet_a_hashes"] = _hashes(work / "A")
        res["fleet_a_rerun"] = _fleet(str(work / "fleet_a.toml"), work / "A", env).finish()
        res["fleet_a_rerun_hashes"] = _hashes(work / "A")

        # fleet B: Ctrl-C while its long member runs; the rerun does the rest
        started = time.time() - 1.0                    # mtimes have coarse resolution
        b = _fleet(str(work / "fleet_b.toml"), work / "B", env)
        b.wait_for("[1/2]")                            # the short member done, and then
        _wait_points("fleet-four-default-s5", 2, started)   # Ctrl-C once the long one logged
        b.proc.send_signal(signal.SIGINT)
        res["fleet_b"] = b.finish()
        res["fleet_b_index_after_interrupt"] = json.loads((work / "B" / "index.json").read_text())
        res["fleet_b_hashes"] = _hashes(work / "B")
        res["fleet_b_rerun"] = _fleet(str(work / "fleet_b.toml"), work / "B", env).finish()
        res["fleet_b_rerun_hashes"] = _hashes(work / "B")

        # the sweep, told the cluster's address by --address
        env_no_address = {k: v for k, v in env.items() if k != "RAY_ADDRESS"}
        t0 = time.time()
        res["sweep"] = Driver(["ude_fit.cli", "sweep", str(work / "sweep.toml"), "--out",
                               str(work / "S"), "--address", cluster.address],
                              env_no_address).finish()
        res["sweep"]["wall_s"] = time.time() - t0
    (work / "results.json").write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    os.environ.setdefault("PYTHONPATH", str(REPO))
    main(Path(sys.argv[1]))
