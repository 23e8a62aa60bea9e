"""A real Ray cluster of local node processes, for the cluster tests and the fleet benchmark.

Each node is ``ray start ... --block`` in its own process group, so a node can be killed
alone (SIGKILL to its group: raylet, workers and what they started) and the whole cluster
stopped without ``ray stop`` (which would stop every Ray process on the machine). Run it in
a network namespace that holds only loopback (:func:`loopback_namespace_command`): Ray
registers a node under the machine's primary address even when told 127.0.0.1, and inside
such a namespace there is none, so every byte stays on loopback.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# fleet B's long member: long enough that a Ctrl-C after its second point finds it running
LONG_AIRSPEEDS = (17.5, 18.0, 18.5, 19.0, 19.5, 20.0, 20.5, 21.0, 21.5, 22.3)
HEAD_PORT = 6379           # free: the namespace is the cluster's own


def loopback_namespace_command(argv: list[str]) -> list[str]:
    """`argv` run in a new network namespace with only loopback, up."""
    inner = "ip link set lo up && exec " + " ".join(_quote(a) for a in argv)
    return ["unshare", "-n", "sh", "-c", inner]


def _quote(a: str) -> str:
    import shlex
    return shlex.quote(a)


def namespace_unavailable() -> str | None:
    """Why a loopback-only namespace cannot be made here (None if it can)."""
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return "unshare (util-linux) and ip (iproute2) are needed"
    r = subprocess.run(loopback_namespace_command(["true"]), capture_output=True, text=True)
    if r.returncode != 0:
        return f"unshare -n failed (needs root): {r.stderr.strip()[:200]}"
    return None


class Node:
    def __init__(self, proc: subprocess.Popen, node_id: str, name: str):
        self.proc, self.node_id, self.name = proc, node_id, name

    def running(self, fragment: str) -> list[int]:
        """Pids of this node's processes (its workers' children too) whose command line
        holds `fragment`: found by the node's name in their environment."""
        return pids_with(f"LAB_RAY_NODE={self.name}".encode(), fragment.encode())

    def kill(self) -> None:
        """Lose the node: SIGKILL to its whole process group."""
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.proc.wait(timeout=30)


class LocalRayCluster:
    """A head node and worker nodes as local processes; use as a context manager."""

    def __init__(self, env: dict | None = None):
        self.temp_dir = tempfile.mkdtemp(prefix="rt")      # short: Ray's socket paths
        self.env = {**os.environ, "PYTHONPATH": str(REPO), "RAY_USAGE_STATS_ENABLED": "0",
                    "LAB_RAY_CLUSTER": self.temp_dir,    # marks every process it starts
                    "RAY_AUTH_MODE": "disabled",      # a private loopback-only cluster
                    **(env or {})}
        self.address = f"127.0.0.1:{HEAD_PORT}"
        self.nodes: list[Node] = []

    def _start(self, args: list[str], num_cpus: int) -> Node:
        before = set(self.alive()) if self.nodes else set()
        name = f"node{len(self.nodes)}"
        proc = subprocess.Popen(["ray", "start", *args, "--node-ip-address", "127.0.0.1",
                                 "--num-cpus", str(num_cpus), "--temp-dir", self.temp_dir,
                                 "--disable-usage-stats", "--block"],
                                env={**self.env, "LAB_RAY_NODE": name},
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                start_new_session=True)
        node = Node(proc, "", name)
        self.nodes.append(node)
        node.node_id = self._wait_new(before, proc)
        return node

    def start_head(self, num_cpus: int = 1) -> Node:
        return self._start(["--head", "--port", str(HEAD_PORT), "--include-dashboard", "false"],
                           num_cpus)

    def add_node(self, num_cpus: int = 1) -> Node:
        return self._start(["--address", self.address], num_cpus)

    def running(self, fragment: str) -> list[int]:
        """Pids of any node's processes whose command line holds `fragment`."""
        return pids_with(f"LAB_RAY_CLUSTER={self.temp_dir}".encode(), fragment.encode())

    def alive(self) -> list[str]:
        """Node ids of the alive nodes (asked of the cluster by a short-lived driver)."""
        code = ("import ray; ray.init(address=%r, log_to_driver=False); "
                "print(' '.join(n['NodeID'] for n in ray.nodes() if n['Alive']))" % self.address)
        r = subprocess.run([sys.executable, "-c", code], env=self.env, capture_output=True,
                           text=True, timeout=120)
        return r.stdout.split() if r.returncode == 0 else []

    def _wait_new(self, before: set, proc: subprocess.Popen, timeout: float = 120) -> str:
        t0 = time.time()
        while time.time() - t0 < timeout:
            if proc.poll() is not None:
                raise RuntimeError(f"ray start exited with {proc.returncode}")
            new = set(self.alive()) - before
            if new:
                return new.pop()
            time.sleep(1.0)
        raise RuntimeError("a Ray node did not join within the timeout")

    def stop(self) -> None:
        """Kill every node (a test cluster holds nothing worth a graceful stop)."""
        for node in self.nodes:
            node.kill()
        _kill_leftovers(self.temp_dir)
        shutil.rmtree(self.temp_dir, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


def pids_with(env_entry: bytes | None, fragment: bytes = b"") -> list[int]:
    """Pids of the other processes whose command line holds `fragment` and, unless None,
    whose environment holds `env_entry`."""
    out = []
    for pid in os.listdir("/proc"):
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ")
            env = ([] if env_entry is None
                   else Path(f"/proc/{pid}/environ").read_bytes().split(b"\0"))
        except OSError:
            continue
        if (env_entry is None or env_entry in env) and fragment in cmd:
            out.append(int(pid))
    return out


def _kill_leftovers(marker: str) -> None:
    """Processes this cluster started that left their node's process group (Ray starts some
    workers in sessions of their own): found by the marker in their environment, killed by
    pid."""
    for pid in pids_with(f"LAB_RAY_CLUSTER={marker}".encode()):
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
