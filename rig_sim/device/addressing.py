"""Which requests the device takes as its own: the unit id (Modbus "slave address").

A device on a serial line has one address, settable, 1..247 (Modbus over serial
line V1.02, 2.2): it answers frames to that address, acts on broadcasts (address
0) of write functions without answering (an answer would collide with the other
slaves' silence), and ignores everything else, broadcast reads included.

Over TCP the device is reached by its IP address and the unit id is for gateways
(Modbus Messaging on TCP/IP Implementation Guide V1.0b, 4.4.2): a device served
directly takes 255 and 0 as "this device" and answers them like its own unit id.
To any other unit id it answers as a gateway with no such slave behind it does:
exception 0B, GATEWAY TARGET DEVICE FAILED TO RESPOND, and acts on nothing.
"""

from __future__ import annotations

import enum
from abc import ABC, abstractmethod
from dataclasses import dataclass

BROADCAST = 0
UNIT_RANGE = (1, 247)
TCP_DIRECT_UNITS = (0, 255)          # "this device" over TCP, whatever its unit id
# The write functions (coils and registers): the only ones a broadcast may carry.
# FC23 also reads, so it has an answer to give and is not broadcast.
BROADCAST_FUNCTIONS = frozenset({5, 6, 15, 16, 22})
GATEWAY_TARGET_FAILED = 0x0B


class Route(enum.Enum):
    ANSWER = "act and answer"
    ACT_SILENTLY = "act, never answer (broadcast write)"
    IGNORE = "neither act nor answer"
    GATEWAY_FAILURE = "answer exception 0B, act on nothing"


def check_unit(unit: int) -> int:
    """The device's own unit id, validated (ValueError names the problem)."""
    lo, hi = UNIT_RANGE
    if isinstance(unit, bool) or not isinstance(unit, int) or not lo <= unit <= hi:
        raise ValueError(f"unit id {unit!r} is not in {lo}..{hi}")
    return unit


@dataclass(frozen=True)
class Addressing(ABC):
    """How one transport routes a request by its unit id and function code."""

    unit: int = 1

    def __post_init__(self):
        check_unit(self.unit)

    @abstractmethod
    def route(self, unit: int, function_code: int) -> Route:
        ...


@dataclass(frozen=True)
class SerialLineAddressing(Addressing):
    """RTU: one address on a shared multi-drop line."""

    def route(self, unit: int, function_code: int) -> Route:
        if unit == self.unit:
            return Route.ANSWER
        if unit == BROADCAST and function_code in BROADCAST_FUNCTIONS:
            return Route.ACT_SILENTLY
        return Route.IGNORE


@dataclass(frozen=True)
class TcpAddressing(Addressing):
    """TCP: the device itself, reached by IP; other unit ids as a gateway would."""

    def route(self, unit: int, function_code: int) -> Route:
        if unit == self.unit or unit in TCP_DIRECT_UNITS:
            return Route.ANSWER
        return Route.GATEWAY_FAILURE
