"""The rig as a network device: Modbus TCP and/or Modbus RTU on a serial port,
serving one register space, with the board's clock (real time, K x real time, or
lockstep).

pymodbus 3.16 is used for framing and transport only: its request PDUs call
`async_getValues`/`async_setValues` on `server.context`, which we point at our
own `RigRegisters`; a request-handler subclass tags each request with its
connection so that control of the rig belongs to one client.
"""

from __future__ import annotations

import asyncio
import collections
import errno
import logging
import os
import socket
import threading
import time
from dataclasses import dataclass

from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.exceptions import ModbusIOException
from pymodbus.pdu import ExceptionResponse
from pymodbus.pdu.device import ModbusDeviceIdentification
from pymodbus.pdu.register_message import ReadWriteMultipleRegistersRequest
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import SimData, SimDevice
from pymodbus.transaction import TransactionManager
from pymodbus.transport import CommType

from ..firmware.board import Board
from . import register_map as M
from .datastore import CURRENT_CLIENT, RigRegisters


class ServiceError(RuntimeError):
    """A start-up problem the user can fix (one-line message)."""


# Modbus over serial line (V1.02, 2.5.1.1): a frame interrupted by silence is
# incomplete and the receiver discards it, so a master recovers from line garbage
# by pausing. pymodbus's RTU framer keeps a partial frame forever (the next valid
# request is then swallowed as its tail). The spec's t3.5 is 1.75 ms above
# 19200 Bd, but host-side delivery (pty relays, USB-serial latency timers) splits
# one frame by more than that, so the receiver allows this much silence.
RTU_FRAME_SILENCE_S = 0.02


def _fc23_counts_ok(pdu: ReadWriteMultipleRegistersRequest) -> bool:
    """The quantity and byte-count checks pymodbus's FC23 makes before it writes."""
    payload = getattr(pdu, "_payload_byte_count", None)
    return (1 <= pdu.read_count <= 125 and 1 <= pdu.write_count <= 121
            and pdu.write_byte_count == 2 * pdu.write_count and payload in (None, pdu.write_byte_count))


def _handler_class(registers: RigRegisters):
    class RigRequestHandler(ServerRequestHandler):
        """pymodbus's handler plus: the request's connection (for control of the
        rig), one queued PDU per scheduled handling (pymodbus keeps only the last
        decoded PDU, so two requests decoded before the first is handled ran the
        second twice and the first never), every complete frame of a read decoded
        and an undecodable frame dropping only itself (pipelined TCP requests),
        the RTU inter-frame silence, and FC23 validating its read part before it
        writes."""

        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self._pending: collections.deque = collections.deque()
            self._rtu = self.comm_params.comm_type == CommType.SERIAL
            self._last_rx = 0.0

        def datagram_received(self, data, addr):
            if self.comm_params.handle_local_echo:
                super().datagram_received(data, addr)
                return
            buf = self.recv_buffer
            if self._rtu:
                now = time.monotonic()
                if buf and now - self._last_rx > RTU_FRAME_SILENCE_S:
                    buf = b""                        # stale partial frame
                self._last_rx = now
            # pymodbus decodes one frame per read and drops a read longer than one
            # frame; decode every complete frame, keep only an incomplete tail
            buf += data
            while buf:
                cut = self.callback_data(buf, addr)
                if cut <= 0:
                    break
                buf = buf[cut:]
            self.recv_buffer = b"" if len(buf) > self.max_buffer_size else buf

        def callback_data(self, data, addr=None):
            # ServerRequestHandler.callback_data, except that an undecodable frame
            # costs only that frame (not the requests pipelined behind it) and
            # each decoded PDU is queued for its own handling
            try:
                used = TransactionManager.callback_data(self, data, addr)
            except ModbusIOException as exc:
                response = ExceptionResponse(exc.fcode or 0, exception_code=ExcCodes.ILLEGAL_FUNCTION,
                                             device_id=exc.dev_id, transaction=exc.transaction_id)
                self.server_send(response, addr)
                return len(data) if self._rtu else (self.framer.decode(data)[0] or len(data))
            if self.last_pdu is not None:
                self._pending.append((self.last_pdu, self.last_addr))
                self.loop.call_soon(self.handle_later)
            return used

        async def handle_request(self):
            if not self._pending:
                return
            self.last_pdu, self.last_addr = self._pending.popleft()
            pdu = self.last_pdu
            if isinstance(pdu, ReadWriteMultipleRegistersRequest) and _fc23_counts_ok(pdu):
                # FC23 writes before it reads; an illegal read part must not write
                # (counts first: those the PDU checks itself, answering 03)
                probe = registers.read(pdu.function_code, pdu.read_address, pdu.read_count, self)
                if isinstance(probe, ExcCodes):
                    response = ExceptionResponse(pdu.function_code, probe)
                    response.transaction_id = pdu.transaction_id
                    response.dev_id = pdu.dev_id
                    self.server_send(response, self.last_addr)
                    return
            token = CURRENT_CLIENT.set(self)
            try:
                await super().handle_request()
            finally:
                CURRENT_CLIENT.reset(token)

        def callback_disconnected(self, exc):
            # a client that goes away gives control back; if it left the rig armed,
            # the watchdog will disarm it (nobody feeds the heartbeat any more)
            registers.release_if_owner(self)
            super().callback_disconnected(exc)

    return RigRequestHandler


def _bind(server, registers: RigRegisters):
    handler = _handler_class(registers)
    server.context = registers
    server.callback_new_connection = lambda: handler(
        server, server.trace_packet, server.trace_pdu, server.trace_connect)
    return server


def _placeholder_device() -> SimDevice:
    # pymodbus insists on a SimDevice at construction; it is replaced by _bind.
    return SimDevice(id=0, simdata=[SimData(1, values=0)])


def _identity(board: Board) -> ModbusDeviceIdentification:
    ident = ModbusDeviceIdentification()
    ident.VendorName = "Virtual CBC Lab"
    ident.ProductCode = board.spec.model
    ident.ProductName = board.spec.model
    ident.ModelName = board.spec.model
    ident.MajorMinorRevision = f"{M.FIRMWARE_VERSION // 100}.{M.FIRMWARE_VERSION % 100:02d}"
    return ident


@dataclass
class Pacing:
    mode: str = "realtime"      # "realtime" (time_scale may be != 1) or "lockstep"
    time_scale: float = 1.0
    tick_s: float = 0.001       # pacer wake-up interval
    slip_s: float = 0.25        # fall this far behind and the pacer counts an overrun and slips


class Pacer(threading.Thread):
    """Advances the board in step with the wall clock (times time_scale)."""

    def __init__(self, registers: RigRegisters, pacing: Pacing):
        super().__init__(name="rig-pacer", daemon=True)
        self.registers = registers
        self.board = registers.board
        self.pacing = pacing
        self.stop_event = threading.Event()
        self.error: BaseException | None = None

    def run(self) -> None:
        b = self.board
        k = self.pacing.time_scale
        rate = b.rate
        max_chunk = max(1, int(rate * k * 0.002))     # ~2 ms of wall time per chunk at most
        t0 = time.monotonic()
        seq0 = b.seq
        self.registers.running = True
        try:
            while not self.stop_event.is_set():
                now = time.monotonic()
                due = seq0 + int((now - t0) * k * rate)
                behind = due - b.seq
                if behind > self.pacing.slip_s * k * rate:
                    b.overruns += 1
                    t0, seq0 = now, b.seq               # a missed deadline: time slips
                    behind = 0
                while behind > 0 and not self.stop_event.is_set():
                    n = min(behind, max_chunk)
                    b.advance(n)
                    behind -= n
                if (self.registers.owner is not None or b.armed) and b.check_watchdog(lockstep=False):
                    self.registers.free_control()
                self.stop_event.wait(self.pacing.tick_s)
        except BaseException as exc:  # surface to the service, don't die silently
            self.error = exc
        finally:
            self.registers.running = False


def port_free(host: str, port: int) -> None:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise ServiceError(f"port {port} on {host} is already in use") from None
            raise ServiceError(f"cannot bind {host}:{port}: {exc.strerror}") from None


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class RigService:
    """Board + registers + clock + transports, run on one asyncio loop."""

    def __init__(self, board: Board, pacing: Pacing, host: str | None = "127.0.0.1",
                 port: int | None = 5020, serial: str | None = None, baudrate: int = 115200):
        if host is None and serial is None:
            raise ServiceError("nothing to serve: give a TCP port or --serial PORT")
        self.board = board
        self.pacing = pacing
        self.registers = RigRegisters(board, lockstep=pacing.mode == "lockstep")
        self.host, self.port = host, port
        self.serial, self.baudrate = serial, baudrate
        self.servers: list = []
        self.pacer: Pacer | None = None

    def check(self) -> None:
        if self.host is not None:
            if self.port == 0:
                self.port = free_port(self.host)
            port_free(self.host, self.port)
        if self.serial is not None and not os.path.exists(self.serial):
            raise ServiceError(f"serial port {self.serial} does not exist")

    async def start(self) -> None:
        self.check()
        ident = _identity(self.board)
        if self.host is not None:
            tcp = ModbusTcpServer(_placeholder_device(), framer=FramerType.SOCKET,
                                  identity=ident, address=(self.host, self.port))
            _bind(tcp, self.registers)
            await tcp.serve_forever(background=True)
            self.servers.append(tcp)
        if self.serial is not None:
            rtu = ModbusSerialServer(_placeholder_device(), framer=FramerType.RTU,
                                     identity=ident, port=self.serial, baudrate=self.baudrate)
            _bind(rtu, self.registers)
            try:
                await rtu.serve_forever(background=True)
            except RuntimeError:
                raise ServiceError(f"cannot open serial port {self.serial}") from None
            self.servers.append(rtu)
        if self.pacing.mode != "lockstep":
            self.pacer = Pacer(self.registers, self.pacing)
            self.pacer.start()

    async def stop(self) -> None:
        if self.pacer is not None:
            self.pacer.stop_event.set()
            self.pacer.join(timeout=5)
        for s in self.servers:
            await s.shutdown()

    async def run_forever(self, stop: asyncio.Event) -> None:
        await self.start()
        try:
            while not stop.is_set():
                if self.pacer is not None and self.pacer.error is not None:
                    raise self.pacer.error
                try:
                    await asyncio.wait_for(stop.wait(), timeout=0.5)
                except asyncio.TimeoutError:
                    pass
        finally:
            await self.stop()


def quiet_pymodbus(verbose: bool = False) -> None:
    """pymodbus logs every malformed frame at ERROR; a device ignores them quietly."""
    logging.getLogger("pymodbus").setLevel(logging.DEBUG if verbose else logging.CRITICAL)
