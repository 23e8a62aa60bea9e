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
from pymodbus.framer import FramerRTU
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
from .addressing import (GATEWAY_TARGET_FAILED, Addressing, Route, SerialLineAddressing, TcpAddressing,
                         check_unit)
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


def _handler_class(registers: RigRegisters, addressing: Addressing):
    class RigRequestHandler(ServerRequestHandler):
        """pymodbus's handler plus: the request's connection (for control of the
        rig), one queued PDU per scheduled handling (pymodbus keeps only the last
        decoded PDU, so two requests decoded before the first is handled ran the
        second twice and the first never), every complete frame of a read decoded
        and an undecodable frame dropping only itself (pipelined TCP requests),
        the RTU inter-frame silence, FC23 validating its read part before it
        writes, and the unit id routing each request (addressing.py)."""

        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self._pending: collections.deque = collections.deque()
            self._rtu = self.comm_params.comm_type == CommType.SERIAL
            self._last_rx = 0.0
            self._gone = False          # disconnected, with requests still queued

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
            if self._rtu and self.recv_buffer:
                self.loop.call_later(RTU_FRAME_SILENCE_S, self._line_silent, self._last_rx)

        def _line_silent(self, rx_time: float) -> None:
            """Silence ends an RTU frame. A frame still held when the line falls silent
            is one the framer could not size: a function code this device does not
            know. With a valid CRC it is a request, answered ILLEGAL FUNCTION."""
            frame = self.recv_buffer
            if self._last_rx != rx_time or len(frame) < 4:
                return
            self.recv_buffer = b""
            crc = int.from_bytes(frame[-2:], "big")
            if FramerRTU.check_CRC(frame[:-2], crc) and self.framer.decoder.lookupPduClass(frame) is None:
                self._answer_unknown(frame[1], frame[0], 0, None)

        def callback_data(self, data, addr=None):
            # ServerRequestHandler.callback_data, except that an undecodable frame
            # costs only that frame (not the requests pipelined behind it), the
            # unit id routes every frame (addressing.py), an unknown function is
            # answered with its own code + 0x80, and each decoded PDU is queued
            # for its own handling
            try:
                used = TransactionManager.callback_data(self, data, addr)
            except ModbusIOException:
                used, unit, tid, pdu_bytes = self.framer.decode(data)
                function_code = pdu_bytes[0] if pdu_bytes else 0
                self._answer_unknown(function_code, unit, tid, addr)
                return len(data) if self._rtu else (used or len(data))
            pdu = self.last_pdu
            if pdu is None:
                return used
            if isinstance(pdu, ExceptionResponse):
                # a request with a code >= 0x81 (pymodbus decodes it as an exception reply)
                self._answer_unknown(pdu.function_code, pdu.dev_id, pdu.transaction_id, addr)
                return used
            route = addressing.route(pdu.dev_id, pdu.function_code)
            if route is Route.GATEWAY_FAILURE:
                self._send_exception(pdu.function_code, GATEWAY_TARGET_FAILED, pdu.dev_id,
                                     pdu.transaction_id, addr)
            elif route is not Route.IGNORE:
                self._pending.append((pdu, self.last_addr, route is Route.ANSWER))
                self.loop.call_soon(self.handle_later)
            return used

        def _answer_unknown(self, function_code, unit, tid, addr):
            """ILLEGAL FUNCTION to a function this device does not serve; the reply's
            function byte is the request's code with the exception bit set (codes
            0x80..0xFF, reserved for replies, already have it: the byte is echoed)."""
            route = addressing.route(unit, function_code)
            if route is Route.ANSWER:
                self._send_exception(function_code, ExcCodes.ILLEGAL_FUNCTION, unit, tid, addr)
            elif route is Route.GATEWAY_FAILURE:
                self._send_exception(function_code, GATEWAY_TARGET_FAILED, unit, tid, addr)

        def _send_exception(self, function_code, code, unit, tid, addr):
            self.server_send(ExceptionResponse(function_code, exception_code=code, device_id=unit,
                                               transaction=tid), addr)

        async def handle_request(self):
            if not self._pending:
                return
            try:
                await self._serve(*self._pending.popleft())
            finally:
                if self._gone and not self._pending:
                    registers.release_if_owner(self)

        async def _serve(self, pdu, addr, answer):
            self.last_pdu, self.last_addr = pdu, addr
            if isinstance(pdu, ReadWriteMultipleRegistersRequest) and _fc23_counts_ok(pdu):
                # FC23 writes before it reads; an illegal read part must not write
                # (counts first: those the PDU checks itself, answering 03)
                probe = registers.read(pdu.function_code, pdu.read_address, pdu.read_count, self)
                if isinstance(probe, ExcCodes):
                    if answer:
                        self._send_exception(pdu.function_code, probe, pdu.dev_id, pdu.transaction_id, addr)
                    return
            token = CURRENT_CLIENT.set(self)
            try:
                response = await pdu.datastore_update(registers, pdu.dev_id)
            except Exception as exc:  # noqa: BLE001
                # a request pymodbus decodes but cannot serve (FC8 with a sub-function
                # it does not know raises KeyError): the function is not served, which
                # is 01 (pymodbus would answer 04 and log a traceback)
                logging.getLogger(__name__).debug("request %s not served: %r", pdu, exc)
                response = ExceptionResponse(pdu.function_code, ExcCodes.ILLEGAL_FUNCTION)
            finally:
                CURRENT_CLIENT.reset(token)
            if answer:
                response.transaction_id = pdu.transaction_id
                response.dev_id = pdu.dev_id
                self.server_send(response, addr)

        def callback_disconnected(self, exc):
            # a client that goes away gives control back; if it left the rig armed,
            # the watchdog will disarm it (nobody feeds the heartbeat any more). The
            # requests it sent before it went are served first, in order, and control
            # goes back after them: released before them, a write among them claimed
            # the rig for a connection that no longer exists, and in lockstep (where
            # the watchdog runs on simulated time, which only a controller advances)
            # nobody could take control again
            self._gone = True
            if not self._pending:
                registers.release_if_owner(self)
            super().callback_disconnected(exc)

    return RigRequestHandler


def _bind(server, registers: RigRegisters, addressing: Addressing):
    handler = _handler_class(registers, addressing)
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
                 port: int | None = 5020, serial: str | None = None, baudrate: int = 115200,
                 unit: int = 1):
        if host is None and serial is None:
            raise ServiceError("nothing to serve: give a TCP port or --serial PORT")
        try:
            self.unit = check_unit(unit)
        except ValueError as exc:
            raise ServiceError(str(exc)) from None
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
            _bind(tcp, self.registers, TcpAddressing(self.unit))
            await tcp.serve_forever(background=True)
            self.servers.append(tcp)
        if self.serial is not None:
            rtu = ModbusSerialServer(_placeholder_device(), framer=FramerType.RTU,
                                     identity=ident, port=self.serial, baudrate=self.baudrate)
            _bind(rtu, self.registers, SerialLineAddressing(self.unit))
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
