"""A rig client generated from the register map.

Speaks to any device that implements `rig_sim.device.register_map` (the only part
of rig_sim the controller may import) over Modbus TCP (`tcp://host:port`), Modbus
RTU on a serial port (`serial:///dev/ttyX` or `serial://COM3`) or RTU framing over
a TCP socket (`socket://host:port`).

Reads of several registers are coalesced into as few requests as the map allows;
writes of several settings go out as one FC16 per contiguous run, so the device
validates them together.
"""

from __future__ import annotations

from dataclasses import dataclass
from urllib.parse import urlparse

import numpy as np
from pymodbus import FramerType
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ModbusException

from rig_sim.device import register_map as M

EXCEPTION_NAMES = {1: "ILLEGAL FUNCTION", 2: "ILLEGAL DATA ADDRESS", 3: "ILLEGAL DATA VALUE",
                   4: "SERVER DEVICE FAILURE", 6: "SERVER DEVICE BUSY"}


class RigError(RuntimeError):
    """The rig answered with a Modbus exception, or did not answer."""

    def __init__(self, message: str, code: int | None = None):
        super().__init__(message)
        self.code = code


@dataclass
class RingBlock:
    """Samples pulled from the ring buffer, in physical units."""
    first_record: int
    sample: np.ndarray       # absolute sample numbers (time = sample / sample_rate)
    data: dict               # field -> float array
    gap: int                 # records lost before this block (overwritten before we read them)


class RigClient:
    def __init__(self, url: str, timeout: float = 1.0, retries: int = 1, device_id: int = 1):
        self.url = url
        u = urlparse(url)
        self.device_id = device_id
        if u.scheme == "tcp":
            self._client = ModbusTcpClient(u.hostname or "127.0.0.1", port=u.port or 502,
                                           timeout=timeout, retries=retries)
        elif u.scheme == "socket":
            self._client = ModbusTcpClient(u.hostname or "127.0.0.1", port=u.port or 502,
                                           framer=FramerType.RTU, timeout=timeout, retries=retries)
        elif u.scheme == "serial":
            port = (u.netloc + u.path) if u.netloc else u.path
            self._client = ModbusSerialClient(port, framer=FramerType.RTU, baudrate=115200,
                                              timeout=timeout, retries=retries)
        else:
            raise ValueError(f"rig address {url!r}: use tcp://HOST:PORT, serial://PORT or socket://HOST:PORT")
        self.identity: dict = {}
        self._fs: dict[str, float] = {}
        self._next_record: int | None = None
        self.rig = "both"            # until the identification is read

    # ---- connection ----------------------------------------------------------------------
    def connect(self) -> dict:
        try:
            ok = self._client.connect()
        except OSError:
            ok = False
        if not ok:
            raise RigError(f"cannot connect to {self.url}")
        names = ["model", "firmware_version", "map_version", "rig_kind", "sample_rate",
                 "ring_capacity", "ring_record_words", "ring_base", "fs_x", "fs_x_dot",
                 "fs_q2", "fs_q2_dot", "fs_control", "fs_parameter"]
        self.identity = self.read(*names)
        if self.identity["map_version"] != M.MAP_VERSION:
            raise RigError(f"{self.url}: register map version {self.identity['map_version']}, "
                           f"this client speaks {M.MAP_VERSION}")
        self.rig = "flutter" if self.identity["rig_kind"] == 0 else "oscillator"
        self._fs = {f: self.identity[s] for f, s in M.RING_SCALES.items()}
        return self.identity

    def close(self) -> None:
        self._client.close()

    def set_timeout(self, seconds: float, retries: int) -> None:
        """How long an answer may take, and how often a request is sent again after one
        that took longer (from the next request on; pymodbus reads both per request)."""
        self._client.comm_params.timeout_connect = seconds
        self._client.retries = self._client.transaction.retries = retries

    @property
    def link(self) -> tuple[float, int]:
        """The answer timeout and retries in force (what `set_timeout` last set)."""
        return self._client.comm_params.timeout_connect, self._client.transaction.retries

    def __enter__(self):
        self.connect()
        return self

    def __exit__(self, *exc):
        self.close()

    # ---- raw access ---------------------------------------------------------------------------
    def _check(self, rr, what: str):
        if rr is None:
            raise RigError(f"{self.url}: no answer to {what}")
        if rr.isError():
            code = getattr(rr, "exception_code", None)
            raise RigError(f"{self.url}: {what} refused: {EXCEPTION_NAMES.get(code, code)}", code)
        return rr

    def _call(self, fn, what: str, *args, **kw):
        try:
            rr = fn(*args, device_id=self.device_id, **kw)
        except (ModbusException, OSError) as exc:      # incl. connection reset / refused
            raise RigError(f"{self.url}: no answer to {what} ({exc})") from None
        return self._check(rr, what)

    def read_words(self, table: str, address: int, count: int) -> list[int]:
        fn = self._client.read_input_registers if table == "input" else self._client.read_holding_registers
        return self._call(fn, f"read {table} {address}+{count}", address, count=count).registers

    def write_words(self, address: int, words: list[int]) -> None:
        self._call(self._client.write_registers, f"write holding {address}+{len(words)}", address, words)

    # ---- by name ---------------------------------------------------------------------------------
    def read(self, *names: str) -> dict:
        regs = sorted((M.BY_NAME[n] for n in names), key=lambda r: (r.table, r.address))
        out: dict = {}
        i = 0
        while i < len(regs):
            table, start = regs[i].table, regs[i].address
            j = i
            end = regs[i].address + regs[i].width
            # coalesce while the run stays contiguous-enough and within one request
            while j + 1 < len(regs) and regs[j + 1].table == table and \
                    regs[j + 1].address + regs[j + 1].width - start <= M.MAX_READ and \
                    regs[j + 1].address - end <= 8 and _all_mapped(table, self.rig, end, regs[j + 1].address):
                j += 1
                end = regs[j].address + regs[j].width
            words = self.read_words(table, start, end - start)
            for reg in regs[i:j + 1]:
                off = reg.address - start
                out[reg.name] = M.decode(reg, words[off:off + reg.width])
            i = j + 1
        return out

    def get(self, name: str):
        return self.read(name)[name]

    def write(self, **settings) -> None:
        regs = sorted((M.BY_NAME[n] for n in settings), key=lambda r: r.address)
        run: list = []
        for reg in regs:
            if reg.table != "holding":
                raise ValueError(f"{reg.name} is read-only")
            if run and reg.address != run[-1].address + run[-1].width:
                self._write_run(run, settings)
                run = []
            run.append(reg)
        if run:
            self._write_run(run, settings)

    def _write_run(self, run, settings) -> None:
        words: list[int] = []
        for reg in run:
            words += M.encode(reg, settings[reg.name])
        self.write_words(run[0].address, words)

    # ---- Fourier estimates ------------------------------------------------------------------------
    def fourier(self, channel: str) -> dict:
        """Mean and variance of the 15 coefficients of one channel, read in one request."""
        base = M.CHANNEL_BASE[channel]
        words = self.read_words("input", base, 62)
        block = M.decode_block("input", base, words)
        mean = np.array([block[f"{channel}_mean_{c}"] for c in M.COEFS])
        var = np.array([block[f"{channel}_var_{c}"] for c in M.COEFS])
        return {"periods": block[f"{channel}_periods"], "mean": mean, "var": var}

    # ---- sample ring ------------------------------------------------------------------------------
    def pull_ring(self, max_records: int | None = None, restart: bool = False) -> RingBlock:
        """Records written since the last pull (the first pull, or restart=True, starts at
        the head and returns nothing). Records overwritten before we got to them, or
        possibly while we read them, are left out and counted in `gap`."""
        pos = self.read("sample_seq", "ring_head")
        head, now = pos["ring_head"], pos["sample_seq"]
        cap = M.RING_CAPACITY
        if self._next_record is None or restart:
            self._next_record = head
        start = self._next_record
        gap = 0
        if head - start > cap - 64:        # keep clear of the record being overwritten
            gap = head - start - (cap - 64)
            start = head - (cap - 64)
        stop = head if max_records is None else min(head, start + max_records)
        per_read = M.MAX_READ // M.RING_RECORD
        chunks = []
        j = start
        while j < stop:
            n = min(per_read, stop - j, cap - j % cap)   # do not run off the end of the ring
            words = self.read_words("input", M.ring_address(j), n * M.RING_RECORD)
            chunks.append(np.asarray(words, dtype=np.uint16).reshape(n, M.RING_RECORD))
            j += n
        raw = np.concatenate(chunks) if chunks else np.zeros((0, M.RING_RECORD), np.uint16)
        self._next_record = stop
        if chunks:
            # The rig kept writing while we read: record j's slot may hold record j + cap
            # once the head has reached j + cap, and a slow read (a busy host, a slow line) can
            # take longer than the clearance above. Such a record would carry the sample
            # number of a lap later, so every record that may have been overwritten by the
            # time the last chunk came back is dropped and counted as lost.
            overwritten = min(len(raw), max(0, self.get("ring_head") - cap + 1 - start))
            raw = raw[overwritten:]
            start += overwritten
            gap += overwritten
        counts = raw.view(np.int16).astype(float)
        data = {f: counts[:, i] / 32767.0 * self._fs[f]
                for i, f in enumerate(M.RING_FIELDS) if f in self._fs}
        data["phase"] = counts[:, M.RING_FIELDS.index("phase")] / 32767.0 * np.pi + np.pi
        # unwrap the 16-bit sample numbers against the absolute counter read with the head
        seq16 = raw[:, 0].astype(np.int64)
        sample = np.zeros(len(seq16), dtype=np.int64)
        if len(seq16):
            last = (now - 1) - ((now - 1 - seq16[-1]) % 65536)
            back = np.concatenate([[0], np.cumsum((seq16[1:] - seq16[:-1]) % 65536)])
            sample = last - (back[-1] - back)
        return RingBlock(start, sample, data, gap)


_MAPPED = {(t, rig): {x for r in M.REGISTERS if r.table == t and r.applies_to(rig)
                      for x in range(r.address, r.address + r.width)}
           for t in ("input", "holding") for rig in ("flutter", "oscillator", "both")}


def _all_mapped(table: str, rig: str, a: int, b: int) -> bool:
    """True if every address in [a, b) is a register of this rig (a read may span it)."""
    return all(x in _MAPPED[(table, rig)] for x in range(a, b))
