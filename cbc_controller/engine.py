"""The real-time engine: runs a CBC plan against a rig.

Every tick of a fixed-rate loop (deadline scheduling, default 200 Hz) it writes
the heartbeat, reads the status block, suspends the plan on a latched fault, and
pulls the sample ring while a record is being taken. In lockstep (the rig's
status says so) a tick also advances the rig a fixed slice of rig time, so a
campaign runs as fast as the machine allows and is reproducible (a slow answer is
then the machine's load, not a lost link: `link_for`).

Lost link: the engine reconnects (bounded wait), takes control again, re-applies
every setting it had written, and throws `RigRestarted` into the plan.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from rig_sim.device import register_map as M

from .client import RigClient, RigError
from .messages import (Arm, Configure, Disarm, Emit, Estimate, PlanContext, Reseed, RigFault,
                       RigRestarted, Settle)

FAULT_BIT = 1 << M.STATUS_BITS["fault"]
LOCKSTEP_BIT = 1 << M.STATUS_BITS["lockstep"]
FOURIER_CHANNELS = ("response", "control", "excitation", "second")


class CampaignAbort(RuntimeError):
    """The campaign cannot go on (rig gone for good, fatal protocol error)."""


@dataclass
class LoopOptions:
    rate_hz: float = 200.0            # host loop rate (wall clock)
    lockstep_slice_s: float = 0.05    # rig seconds advanced per tick in lockstep
    reconnect_s: float = 30.0         # how long to keep trying a lost rig
    max_settle_rig_s: float = 120.0   # a Settle that takes longer is answered with timed_out
    watchdog_s: float = 2.0           # watchdog timeout the engine asks the rig for


REALTIME_ANSWER_S = 2.0     # a real-time rig answers within a tick or two; 2 s is a lost link
REALTIME_RETRIES = 1        # ...and a request lost once is sent again


def link_for(opt: LoopOptions, lockstep: bool) -> tuple[float, int]:
    """The answer timeout and retries for a rig, by its clock. A real-time rig that does not
    answer within `REALTIME_ANSWER_S` is treated as lost (the engine then reconnects). A
    lockstep rig's answers wait on the simulation, whose pace is the machine's load, not
    the link's health: a late answer is waited for as long as a lost rig would be, and never
    asked for twice (an `advance` sent again would advance the rig twice, and the campaign
    would no longer repeat)."""
    return (opt.reconnect_s, 0) if lockstep else (REALTIME_ANSWER_S, REALTIME_RETRIES)


@dataclass
class LoopStats:
    """The loop's own timing, for the log."""
    ticks: int = 0
    overruns: int = 0
    lateness: list = field(default_factory=list)   # seconds, one per tick (bounded)

    def add(self, late: float) -> None:
        self.ticks += 1
        if len(self.lateness) < 200_000:
            self.lateness.append(late)

    def summary(self) -> dict:
        lat = np.asarray(self.lateness) if self.lateness else np.zeros(1)
        return {"ticks": self.ticks, "overruns": self.overruns,
                "lateness_p50_s": float(np.percentile(lat, 50)),
                "lateness_p99_s": float(np.percentile(lat, 99)),
                "lateness_max_s": float(lat.max())}

    def take(self) -> dict:
        s = self.summary()
        self.lateness = []
        return s


class Engine:
    def __init__(self, rig: RigClient, options: LoopOptions | None = None, subscribers=()):
        self.rig = rig
        self.opt = options or LoopOptions()
        self.subscribers = list(subscribers)
        self.applied: dict = {}           # every setting written, re-applied after a reconnect
        self.armed = False
        self.lockstep = False
        self.stats = LoopStats()
        self.point_stats = LoopStats()
        self._heartbeat = 0
        self._next_deadline = 0.0
        self._config_periods = 0
        self._status: dict = {}
        self._link_lost_since_arm = False

    # ------------------------------------------------------------------ documents
    def emit(self, kind: str, doc: dict) -> None:
        if kind == "point":
            doc.setdefault("loop", self.point_stats.take())
        for sub in self.subscribers:
            sub(kind, doc)

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> dict:
        identity = self.rig.connect()
        self._take_control()
        return identity

    def _take_control(self) -> None:
        self.rig.write(control=1)
        self.rig.write(watchdog_timeout=self.opt.watchdog_s)
        self.lockstep = bool(self.rig.get("status") & LOCKSTEP_BIT)
        # on every take of control: a rig back on the same address may keep the other clock
        self.rig.set_timeout(*link_for(self.opt, self.lockstep))
        self._next_deadline = time.monotonic()

    def close(self) -> None:
        try:
            self.rig.write(command=2)
            self.rig.write(control=0)
        except RigError:
            pass
        self.rig.close()

    # ------------------------------------------------------------------ ticking
    def _sleep_to_deadline(self) -> None:
        period = 1.0 / self.opt.rate_hz
        self._next_deadline += period
        now = time.monotonic()
        if now < self._next_deadline:
            time.sleep(self._next_deadline - now)
            now = time.monotonic()
        late = now - self._next_deadline
        if late > period:                       # missed whole deadlines: count and re-phase
            missed = int(late // period)
            self.stats.overruns += missed
            self.point_stats.overruns += missed
            self._next_deadline += missed * period
        self.stats.add(late)
        self.point_stats.add(late)

    def tick(self) -> dict:
        """One loop iteration; returns the status block. Raises RigFault on a latched fault."""
        if self.lockstep:
            n = max(1, int(round(self.opt.lockstep_slice_s * self.rig.identity["sample_rate"])))
            self._call(lambda: self.rig.write(advance=n))
            self.stats.add(0.0)
            self.point_stats.add(0.0)
        else:
            self._sleep_to_deadline()
        self._heartbeat = (self._heartbeat + 1) & 0xFFFF
        self._call(lambda: self.rig.write(heartbeat=self._heartbeat))
        st = self._call(lambda: self.rig.read("status", "fault_code", "sample_seq", "periods"))
        self._status = st
        if st["status"] & FAULT_BIT:
            self._handle_fault(st["fault_code"])
        return st

    def _handle_fault(self, code: int) -> None:
        text = M.FAULT_CODES.get(code, "unknown")
        self._call(lambda: self.rig.write(command=2))       # disarm
        self.armed = False
        self.emit("fault", {"code": code, "text": text, "rig_time": self.rig_time()})
        self._call(lambda: self.rig.write(command=3))       # reset the latch; the plan re-arms
        if code == M.FAULT_WATCHDOG and self._link_lost_since_arm:
            # nobody fed the heartbeat while the link was down: the lost link's own doing,
            # which the plan answers as it answers the lost link, by repeating the point
            raise RigRestarted(f"{text} while the link was down")
        raise RigFault(code, text)

    def rig_time(self) -> float:
        return self._status.get("sample_seq", 0) / self.rig.identity["sample_rate"]

    # ------------------------------------------------------------------ link
    def _call(self, fn):
        try:
            return fn()
        except RigError as exc:
            if exc.code is not None:
                raise                              # a protocol answer, not a lost link
            self._reconnect(exc)
            raise RigRestarted(str(exc)) from None

    def _reconnect(self, why: Exception) -> None:
        self.emit("link", {"event": "lost", "error": str(why), "time": time.time()})
        deadline = time.monotonic() + self.opt.reconnect_s
        while True:
            self.rig.close()
            try:
                self.rig.connect()
                self._take_control()
                if self.applied:
                    self.rig.write(**self.applied)
                self.armed = False
                # the new rig's period counter starts afresh: count from it
                self._config_periods = self.rig.get("periods")
                self._link_lost_since_arm = True
                self.emit("link", {"event": "restored", "time": time.time()})
                return
            except RigError:
                if time.monotonic() > deadline:
                    raise CampaignAbort(f"rig at {self.rig.url} lost and not back within "
                                        f"{self.opt.reconnect_s:g} s") from None
                time.sleep(0.5)

    # ------------------------------------------------------------------ messages
    def execute(self, msg):
        if isinstance(msg, Configure):
            self._call(lambda: self.rig.write(**msg.settings))
            self.applied.update(msg.settings)
            self._config_periods = self._call(lambda: self.rig.get("periods"))
            return None
        if isinstance(msg, Arm):
            try:
                self._call(lambda: self.rig.write(command=1))
            except RigError as exc:
                if exc.code != 4:                   # 4: refused because a fault is latched
                    raise
                code = self._call(lambda: self.rig.get("fault_code"))
                self._handle_fault(code)            # raises RigFault (or RigRestarted)
            self.armed = True
            self._link_lost_since_arm = False
            return None
        if isinstance(msg, Disarm):
            self._call(lambda: self.rig.write(command=2))
            self.armed = False
            return None
        if isinstance(msg, Reseed):
            if self.lockstep:
                self._call(lambda: self.rig.write(noise_seed=msg.seed))
                self.armed = False
                self._config_periods = self._call(lambda: self.rig.get("periods"))
            return None
        if isinstance(msg, Settle):
            return self._settle(msg)
        if isinstance(msg, Emit):
            self.emit(msg.kind, msg.doc)
            return None
        raise TypeError(f"the engine does not know the message {msg!r}")

    def _settle(self, msg: Settle) -> Estimate:
        target = self._config_periods + msg.periods
        t0 = self.rig_time()
        timed_out = False
        while True:
            st = self.tick()
            if st["periods"] >= target:
                break
            if self.rig_time() - t0 > self.opt.max_settle_rig_s:
                timed_out = True
                break
        samples = None
        if msg.record_s > 0 and not timed_out:
            samples = self._record(msg.record_s)
        est = self._estimate()
        est.samples = samples
        est.waited_s = self.rig_time() - t0
        if timed_out:
            est.frequency = float("nan")
        return est

    def _record(self, seconds: float) -> dict:
        self._call(lambda: self.rig.pull_ring(restart=True))
        blocks = []
        t_end = self.rig_time() + seconds
        gaps = 0
        while self.rig_time() < t_end:
            self.tick()
            b = self._call(lambda: self.rig.pull_ring())
            gaps += b.gap
            blocks.append(b)
        if not blocks:
            return {}
        out = {k: np.concatenate([b.data[k] for b in blocks]) for k in blocks[0].data}
        out["sample"] = np.concatenate([b.sample for b in blocks])
        out["gap_records"] = gaps
        return out

    def _estimate(self) -> Estimate:
        fourier = {}
        for ch in FOURIER_CHANNELS:
            f = self._call(lambda ch=ch: self.rig.fourier(ch))
            fourier[ch] = {"mean": f["mean"], "var": f["var"]}
        r = self._call(lambda: self.rig.read("frequency_estimate", "frequency_variance",
                                              "periods", "sample_seq"))
        return Estimate(fourier=fourier, frequency=r["frequency_estimate"],
                        frequency_var=r["frequency_variance"], periods=r["periods"],
                        rig_time=r["sample_seq"] / self.rig.identity["sample_rate"])

    # ------------------------------------------------------------------ running a plan
    def run(self, plan, context: PlanContext) -> str:
        """Drive the plan to its end; returns why it ended."""
        gen = plan(context)
        result, exc = None, None
        while True:
            try:
                msg = gen.throw(exc) if exc is not None else gen.send(result)
            except StopIteration:
                return "completed"
            exc, result = None, None
            try:
                result = self.execute(msg)
            except (RigFault, RigRestarted) as e:
                exc = e
