"""Modbus conformance of the rig, proven with masters that are not the project's
client (nor pymodbus, which the rig itself uses): pyModbusTCP (TCP), modbus-tk (TCP
and RTU), minimalmodbus (RTU over a socat pty), and a raw socket where the question
is the bytes on the wire.

One aerofoil rig in --lockstep (nothing moves unless a client advances it) serves
TCP and RTU at once, on unit id UNIT (not the default 1, so that routing by unit is
visible). Expected values come from the register map (`rig_sim.device.register_map`),
the rig's announcement and the rig's own board, never from numbers typed here.
Every test that writes gives control of the rig back (as the datasheet requires).
"""

from __future__ import annotations

import contextlib
import shutil
import socket
import struct
import time

import minimalmodbus
import modbus_tk.defines as cst
import pytest
import serial
from modbus_tk import modbus_rtu, modbus_tcp
from modbus_tk.exceptions import ModbusError
from pyModbusTCP import utils as mbtcp_utils
from pyModbusTCP.client import ModbusClient

from rig_sim.device import register_map as M
from rig_sim.device.addressing import GATEWAY_TARGET_FAILED
from rig_sim.firmware.board import Board, RigOptions
from rig_sim.harness import PtyPair, RigProcess

UNIT = 17
RIG = "flutter"
ILLEGAL_FUNCTION, ILLEGAL_ADDRESS, ILLEGAL_VALUE, BUSY = 1, 2, 3, 6
BAUD = 115200
RTU_SILENCE_S = 0.04          # above the device's 20 ms inter-frame silence
REG = M.BY_NAME


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    if shutil.which("socat") is None:
        pytest.skip("socat is not installed (.ci/run installs it)")
    folder = tmp_path_factory.mktemp("conformance")
    cable = PtyPair(folder)
    proc = RigProcess("--rig", RIG, "--lockstep", "--port", "0", "--serial", cable.b,
                      "--unit", str(UNIT), "--verbose", stderr_file=folder / "rig.log")
    proc.line = cable.a
    yield proc
    proc.stop()
    cable.close()
    tracebacks = proc.stderr().count("Traceback")
    assert tracebacks == 0, f"{tracebacks} tracebacks inside the rig (--verbose log)"


# ---- the masters -----------------------------------------------------------------------------
def mbtcp(rig, unit: int = UNIT) -> ModbusClient:
    return ModbusClient(host="127.0.0.1", port=rig.port, unit_id=unit, timeout=2.0, auto_open=True)


@contextlib.contextmanager
def tk_tcp(rig):
    master = modbus_tcp.TcpMaster("127.0.0.1", rig.port, timeout_in_sec=2.0)
    try:
        yield master
    finally:
        master.close()


@contextlib.contextmanager
def tk_rtu(rig):
    time.sleep(RTU_SILENCE_S)
    master = modbus_rtu.RtuMaster(serial.Serial(rig.line, baudrate=BAUD))
    master.set_timeout(2.0)
    try:
        yield master
    finally:
        master.close()


@contextlib.contextmanager
def minimal(rig, unit: int = UNIT, timeout: float = 2.0):
    time.sleep(RTU_SILENCE_S)
    inst = minimalmodbus.Instrument(rig.line, unit)
    inst.serial.baudrate = BAUD
    inst.serial.timeout = timeout
    inst.clear_buffers_before_each_transaction = True
    try:
        yield inst
    finally:
        inst.serial.close()


def tk_code(call) -> int:
    with pytest.raises(ModbusError) as exc:
        call()
    return exc.value.get_exception_code()


def words(name: str, value) -> list[int]:
    return M.encode(REG[name], value)


def in_range(name: str, fraction: float) -> float:
    lo, hi = REG[name].range_for(RIG)
    return float(struct.unpack(">f", struct.pack(">f", lo + fraction * (hi - lo)))[0])   # a float32


def holding_block(rig) -> list[int]:
    """Every holding register of the rig from address 0 to the last target coefficient,
    read with pyModbusTCP in map-sized runs (the parameter register of the other rig is a gap)."""
    c = mbtcp(rig)
    out = {}
    for reg in M.REGISTERS:
        if reg.table == "holding" and reg.applies_to(RIG):
            got = c.read_holding_registers(reg.address, reg.width)
            assert got is not None, (reg.name, c.last_error_as_txt, c.last_except_as_txt)
            out[reg.name] = got
    c.close()
    return out


# ---- identification and readings --------------------------------------------------------------
def test_identification_reads_alike_with_every_master(rig):
    assert rig.info["unit"] == UNIT
    model_reg = REG["model"]
    c = mbtcp(rig)
    words_tcp = c.read_input_registers(model_reg.address, model_reg.width)
    c.close()
    assert M.decode(model_reg, words_tcp) == rig.info["model"]
    with tk_tcp(rig) as m:
        assert list(m.execute(UNIT, cst.READ_INPUT_REGISTERS, model_reg.address, model_reg.width)) == words_tcp
    with tk_rtu(rig) as m:
        assert list(m.execute(UNIT, cst.READ_INPUT_REGISTERS, model_reg.address, model_reg.width)) == words_tcp
    with minimal(rig) as inst:
        assert inst.read_string(model_reg.address, model_reg.width, functioncode=4) == rig.info["model"].ljust(16, "\0")
        assert inst.read_register(REG["firmware_version"].address, functioncode=4) == M.FIRMWARE_VERSION
        assert inst.read_register(REG["map_version"].address, functioncode=4) == M.MAP_VERSION
        rate = inst.read_float(REG["sample_rate"].address, functioncode=4, byteorder=minimalmodbus.BYTEORDER_BIG)
    assert rate == Board(RigOptions(kind=RIG)).rate


# ---- function codes and word order --------------------------------------------------------------
def test_fc16_float_written_by_tcp_reads_back_big_endian_everywhere(rig):
    """f32, high word first: written by pyModbusTCP (FC16), read by modbus-tk over TCP
    and RTU (FC3) and by minimalmodbus with BYTEORDER_BIG."""
    reg = REG["airspeed"]
    c = mbtcp(rig)
    before = c.read_holding_registers(reg.address, 2)
    value = in_range("airspeed", 0.3125)
    assert c.write_multiple_registers(reg.address, mbtcp_utils.long_list_to_word(
        [mbtcp_utils.encode_ieee(value)], big_endian=True)), c.last_except_as_txt
    try:
        expected = words("airspeed", value)
        assert c.read_holding_registers(reg.address, 2) == expected
        with tk_tcp(rig) as m:
            assert list(m.execute(UNIT, cst.READ_HOLDING_REGISTERS, reg.address, 2)) == expected
        with tk_rtu(rig) as m:
            assert list(m.execute(UNIT, cst.READ_HOLDING_REGISTERS, reg.address, 2)) == expected
        with minimal(rig) as inst:
            assert inst.read_float(reg.address, functioncode=3, byteorder=minimalmodbus.BYTEORDER_BIG) == value
    finally:
        assert c.write_multiple_registers(reg.address, before)
        assert c.write_single_register(REG["control"].address, 0)
        c.close()


def test_fc6_fc22_fc23_over_rtu_and_tcp(rig):
    navg = REG["navg"]
    lo, hi = navg.range_for(RIG)
    before = holding_block(rig)
    with tk_rtu(rig) as m:
        m.execute(UNIT, cst.WRITE_SINGLE_REGISTER, navg.address, output_value=hi)           # FC6
        assert mbtcp(rig).read_holding_registers(navg.address, 1) == [hi]
        # FC22: (current AND and_mask) OR (or_mask AND NOT and_mask) -> lo
        m.execute(UNIT, cst.MASK_WRITE_REGISTER, navg.address, and_mask=0, or_mask=lo)
        assert mbtcp(rig).read_holding_registers(navg.address, 1) == [lo]
        m.execute(UNIT, cst.WRITE_SINGLE_REGISTER, navg.address, output_value=before["navg"][0])
        m.execute(UNIT, cst.WRITE_SINGLE_REGISTER, REG["control"].address, output_value=0)
    with tk_tcp(rig) as m:
        # FC23: write the heartbeat, read the settings block in one request
        hb = REG["heartbeat"]
        got = m.execute(UNIT, cst.READ_WRITE_MULTIPLE_REGISTERS, 0, 14, output_value=[0x1234],
                        write_starting_address_fc23=hb.address)
        assert got[hb.address] == 0x1234 and got[0] == 1        # heartbeat stored, control now ours
        m.execute(UNIT, cst.WRITE_SINGLE_REGISTER, REG["control"].address, output_value=0)
    after = holding_block(rig)
    after.pop("heartbeat"), before.pop("heartbeat")
    assert after == before


def test_u32_word_order_with_the_advance_register(rig):
    """advance (u32, high word first) written by minimalmodbus as a long advances the
    lockstep simulation by exactly that many samples (sample_seq, u32, read by pyModbusTCP)."""
    n = 0x10000 + 4321                   # both words non-zero
    c = mbtcp(rig)
    seq = REG["sample_seq"]
    s0 = mbtcp_utils.word_list_to_long(c.read_input_registers(seq.address, 2), big_endian=True)[0]
    with minimal(rig, timeout=30.0) as inst:
        inst.write_long(REG["advance"].address, n, byteorder=minimalmodbus.BYTEORDER_BIG)
        assert inst.read_long(REG["advance"].address, functioncode=3, byteorder=minimalmodbus.BYTEORDER_BIG) == n
        inst.write_register(REG["control"].address, 0, functioncode=6)
    s1 = mbtcp_utils.word_list_to_long(c.read_input_registers(seq.address, 2), big_endian=True)[0]
    c.close()
    assert s1 - s0 == n


# ---- exceptions -----------------------------------------------------------------------------------
def _unmapped_holding() -> int:
    used = {a for r in M.REGISTERS if r.table == "holding" for a in range(r.address, r.address + r.width)}
    return next(a for a in range(max(used) + 2) if a not in used)


def test_illegal_address_02_with_every_master(rig):
    gap = _unmapped_holding()
    c = mbtcp(rig)
    assert c.read_holding_registers(gap, 1) is None and c.last_except == ILLEGAL_ADDRESS
    c.close()
    other = REG["forcing_amplitude"]          # the other rig's parameter register
    with tk_tcp(rig) as m:
        assert tk_code(lambda: m.execute(UNIT, cst.READ_HOLDING_REGISTERS, other.address, 2)) == ILLEGAL_ADDRESS
    with tk_rtu(rig) as m:
        assert tk_code(lambda: m.execute(UNIT, cst.READ_HOLDING_REGISTERS, gap, 1)) == ILLEGAL_ADDRESS
    with minimal(rig) as inst:
        with pytest.raises(minimalmodbus.IllegalRequestError, match="illegal data address"):
            inst.read_register(gap, functioncode=3)


def test_illegal_value_03_changes_nothing(rig):
    before = holding_block(rig)
    lo, hi = REG["airspeed"].range_for(RIG)
    c = mbtcp(rig)
    assert not c.write_multiple_registers(REG["airspeed"].address, words("airspeed", 2 * hi + 1))
    assert c.last_except == ILLEGAL_VALUE
    c.close()
    with tk_rtu(rig) as m:
        assert tk_code(lambda: m.execute(UNIT, cst.WRITE_MULTIPLE_REGISTERS, REG["trip"].address,
                                         output_value=words("trip", float("nan")))) == ILLEGAL_VALUE
        m.execute(UNIT, cst.WRITE_SINGLE_REGISTER, REG["control"].address, output_value=0)
    with minimal(rig) as inst:
        with pytest.raises(minimalmodbus.IllegalRequestError, match="illegal data value"):
            inst.write_register(REG["navg"].address, REG["navg"].range_for(RIG)[1] + 1, functioncode=6)
        inst.write_register(REG["control"].address, 0, functioncode=6)
    assert holding_block(rig) == before


def test_illegal_function_01_carries_the_request_code(rig):
    """Unknown function codes answer 01 with the request's code + 0x80 (0x41 -> C1);
    codes 0x80..0xFF, reserved for replies, answer 01 with their own code (already
    carrying the exception bit). Over TCP (pyModbusTCP, raw) and RTU (modbus-tk,
    whose exception check also needs the reply's function byte above 0x80)."""
    c = mbtcp(rig)
    for fc in (0x41, 0x64, 0x80, 0xC1, 0xFF):
        assert c.custom_request(bytes([fc, 0, 0])) is None
        assert c.last_except == ILLEGAL_FUNCTION, hex(fc)
    # a diagnostics (FC8) sub-function the device does not serve
    assert c.custom_request(bytes.fromhex("08277600")) is None and c.last_except == ILLEGAL_FUNCTION
    c.close()
    with socket.create_connection(("127.0.0.1", rig.port), timeout=2) as s:
        for tid, fc in enumerate([0x80, *range(0x40, 0x100, 7)], 1):
            if fc in _SERVED:
                continue
            s.sendall(struct.pack(">HHHBB", tid, 0, 4, UNIT, fc) + b"\x00\x00")
            assert s.recv(64) == struct.pack(">HHHBBB", tid, 0, 3, UNIT, fc | 0x80, ILLEGAL_FUNCTION), hex(fc)
    with tk_rtu(rig) as m:
        # 0x80..0xFF are sized as exception frames; an unknown code below 0x80 cannot
        # be sized, and the device takes the frame as ended when the line falls silent
        for fc, body in ((0xC1, b"\x00"), (0xFF, b"\x00"), (0x41, b"\x00\x00"), (0x64, b"\x01\x02\x03\x04")):
            code = tk_code(lambda: m.execute(UNIT, cst.RAW, 0, pdu=bytes([fc]) + body, expected_length=5))
            assert code == ILLEGAL_FUNCTION, hex(fc)


_SERVED = {1, 2, 3, 4, 5, 6, 7, 8, 11, 12, 15, 16, 17, 20, 21, 22, 23, 24, 43}


def test_second_master_gets_busy_06(rig):
    c = mbtcp(rig)
    kp = REG["kp"]
    before = c.read_holding_registers(kp.address, 2)
    assert c.write_multiple_registers(kp.address, before)           # implicit claim
    try:
        with tk_tcp(rig) as m:
            assert tk_code(lambda: m.execute(UNIT, cst.WRITE_MULTIPLE_REGISTERS, kp.address,
                                             output_value=before)) == BUSY
            assert m.execute(UNIT, cst.READ_HOLDING_REGISTERS, REG["control"].address, 1) == (2,)
        with minimal(rig) as inst:
            with pytest.raises(minimalmodbus.SlaveDeviceBusyError):
                inst.write_register(REG["navg"].address, 1, functioncode=6)
    finally:
        assert c.write_single_register(REG["control"].address, 0)
        c.close()


# ---- unit ids and broadcast ---------------------------------------------------------------------
def test_tcp_unit_ids_0_255_are_this_device_others_get_gateway_0b(rig):
    model = REG["model"]
    expected = M.encode(model, rig.info["model"])
    for unit in (UNIT, 0, 255):
        c = mbtcp(rig, unit)
        assert c.read_input_registers(model.address, model.width) == expected, unit
        c.close()
    before = holding_block(rig)
    for unit in (1, UNIT + 1, 247):
        c = mbtcp(rig, unit)
        assert c.read_input_registers(model.address, model.width) is None
        assert c.last_except == GATEWAY_TARGET_FAILED, unit
        assert not c.write_multiple_registers(REG["airspeed"].address, words("airspeed", in_range("airspeed", 0.5)))
        assert c.last_except == GATEWAY_TARGET_FAILED, unit
        c.close()
    with tk_tcp(rig) as m:
        assert tk_code(lambda: m.execute(UNIT + 1, cst.READ_HOLDING_REGISTERS, 0, 1)) == GATEWAY_TARGET_FAILED
    assert holding_block(rig) == before


def test_rtu_other_units_and_broadcast_reads_get_no_answer(rig):
    before = holding_block(rig)
    with minimal(rig, unit=UNIT + 1, timeout=0.3) as inst:
        with pytest.raises(minimalmodbus.NoResponseError):
            inst.read_register(REG["navg"].address, functioncode=3)
        with pytest.raises(minimalmodbus.NoResponseError):
            inst.write_register(REG["navg"].address, 1, functioncode=6)
    with tk_rtu(rig) as m:
        m.set_timeout(0.3)
        # a broadcast read: modbus-tk sends it (minimalmodbus refuses to) and must hear nothing
        with pytest.raises(Exception, match="(?i)response|timeout|length"):
            m.execute(0, cst.READ_HOLDING_REGISTERS, 0, 1)
        m.set_timeout(2.0)
        time.sleep(RTU_SILENCE_S)
        assert m.execute(UNIT, cst.READ_INPUT_REGISTERS, REG["map_version"].address, 1) == (M.MAP_VERSION,)
    assert holding_block(rig) == before


def test_rtu_broadcast_writes_are_applied_and_never_answered(rig):
    kp, navg = REG["kp"], REG["navg"]
    before = holding_block(rig)
    value = in_range("kp", 0.625)
    n = navg.range_for(RIG)[1] - 1
    with minimal(rig, unit=0) as inst:               # minimalmodbus: broadcast = no reply awaited
        inst.write_float(kp.address, value, byteorder=minimalmodbus.BYTEORDER_BIG)    # FC16
        inst.write_register(navg.address, n, functioncode=6)                         # FC6
        time.sleep(0.1)
        assert inst.serial.in_waiting == 0, "the device answered a broadcast"
    c = mbtcp(rig)
    assert c.read_holding_registers(kp.address, 2) == words("kp", value)
    assert c.read_holding_registers(navg.address, 1) == [n]
    assert c.read_holding_registers(REG["control"].address, 1) == [2]    # held by the serial line
    c.close()
    with minimal(rig) as inst:
        inst.write_register(navg.address, before["navg"][0], functioncode=6)
        inst.write_registers(kp.address, before["kp"])
        inst.write_register(REG["control"].address, 0, functioncode=6)
    assert holding_block(rig) == before
