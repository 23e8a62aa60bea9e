"""A fleet member's task without Ray: how the end of its controller process is read. A
controller killed from outside (its node lost) is the machine's trouble and must come back
as an error Ray retries, never as the member's failure; one that dies of a crash fails the
member with the signal named. The processes and signals are real."""

from __future__ import annotations

import os
import signal
import tempfile
import threading
import time
import pytest

from cbc_controller.fleet.member import ControllerKilled, run_member
from cbc_controller.fleet.options import Member, RigSettings
from tests.cluster_scenario import FLUTTER
from tests.ray_cluster import LONG_AIRSPEEDS, pids_with

# the cluster scenario's long lockstep flutter campaign: long enough to be found running
CAMPAIGN = FLUTTER.format(name="long", values=str(list(LONG_AIRSPEEDS)))


def _member(name: str) -> Member:
    return Member(id=name, campaign="long.toml", rig="flutter",
                  settings=RigSettings(label="clean"), seed=1, campaign_toml=CAMPAIGN)


def _controller_of(member_id: str, timeout: float = 60.0) -> int:
    """The pid of the controller running `member_id` (its scratch folder names it)."""
    fragment = f"cbc_controller.cli run {tempfile.gettempdir()}/fleet-{member_id}-".encode()
    t0 = time.time()
    while time.time() - t0 < timeout:
        if pids := pids_with(None, fragment):
            return pids[0]
        time.sleep(0.1)
    raise AssertionError(f"no controller for {member_id} started")


def _run_and_signal(member_id: str, sig: signal.Signals):
    """run_member in a thread; `sig` sent to its controller once it has run a second."""
    outcome: dict = {}

    def target():
        try:
            outcome["result"] = run_member(_member(member_id))
        except Exception as exc:          # noqa: BLE001  (what the task would raise to Ray)
            outcome["error"] = exc
    worker = threading.Thread(target=target)
    worker.start()
    pid = _controller_of(member_id)
    time.sleep(1.0)
    os.kill(pid, sig)
    worker.join(timeout=120)
    assert not worker.is_alive()
    return outcome


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_a_controller_killed_from_outside_is_raised_for_a_retry(sig):
    outcome = _run_and_signal(f"killed{sig.value}", sig)
    assert "result" not in outcome, outcome
    err = outcome["error"]
    assert isinstance(err, ControllerKilled), err
    assert sig.name in str(err) and f"killed{sig.value}" in str(err)


def test_a_controller_that_crashes_fails_the_member_with_the_signal_named():
    outcome = _run_and_signal("crashed", signal.SIGSEGV)
    result = outcome["result"]
    assert result.status == "failed"
    assert "SIGSEGV" in result.error, result.error
