"""Pololu Maestro servo controllers (Micro and Mini Maestro) over their serial command set.

Byte formats follow the Maestro user's guide, section "Serial Servo Commands":

================  ==================================  ===================================
command           compact protocol                    Pololu protocol (device number dd)
================  ==================================  ===================================
Set Target        84 ch lo hi                         AA dd 04 ch lo hi
Set Speed         87 ch lo hi                         AA dd 07 ch lo hi
Set Acceleration  89 ch lo hi                         AA dd 09 ch lo hi
Get Position      90 ch      -> lo8 hi8               AA dd 10 ch      -> lo8 hi8
Get Moving State  93         -> 00 | 01               AA dd 13         -> 00 | 01
Get Errors        A1         -> lo8 hi8               AA dd 21         -> lo8 hi8
Go Home           A2                                  AA dd 22
================  ==================================  ===================================

Command values (targets, speeds, accelerations) go out as two 7-bit data bytes, low bits first,
because every data byte must have its most significant bit clear; replies are plain 8-bit
bytes, low byte first. Targets are in quarter-microseconds; speed in 0.25 us per 10 ms.
The Pololu protocol lets several devices share one line; it is the compact command byte with
its MSB cleared, after 0xAA and the device number (12 by default).

Quirks a host must live with (user's guide and Pololu's forum):

- Models: the Micro Maestro has 6 channels, the Mini Maestros 12, 18 or 24 (:data:`MODELS`).
- Get Moving State on the Micro Maestro 6 can answer 0 while an output still ramps (a firmware
  bug Pololu documents; Mini Maestros are not affected). It is only used as a hint here: the
  host waits until Get Position reads back every target (:class:`Maestro`).
- Each channel's Min and Max (Control Center, Channel Settings; factory 992 and 2000 us) clamp
  every target, so a wider command stops at the range's end: reported as such, never recorded.
- On an error (a garbled byte, a serial timeout) each channel goes to its "On startup or error"
  setting: off by default, or a home position. Collect re-reads errors and positions after each
  measurement and measures the row again (:meth:`ServoController.dropped_targets`).
- In the serial mode "UART, detect baud rate" the first byte must be 0xAA, from which the
  Maestro measures the baud rate. Every Pololu-protocol command starts with 0xAA, so that
  protocol needs nothing more; with the compact protocol ``auto_baud`` sends a lone 0xAA first.
  It is not sent unasked because a Maestro not detecting a baud rate takes it for the start of
  a Pololu-protocol command cut short (a protocol error).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Literal

from bayesrob.hardware.controller import ArgumentError, HardwareError, ServoController

SET_TARGET = 0x84
SET_SPEED = 0x87
SET_ACCELERATION = 0x89
GET_POSITION = 0x90
GET_MOVING_STATE = 0x93
GET_ERRORS = 0xA1
GO_HOME = 0xA2
SET_MULTIPLE_TARGETS = 0x9F
POLOLU_START = 0xAA
DEFAULT_DEVICE = 12
MAX_CHANNELS = 24  # the Mini Maestro 24 is the largest
MAX_14BIT = 0x3FFF
BAUD_INDICATION = 0xAA
FACTORY_RANGE_US = (992.0, 2000.0)  # each channel's Min and Max as shipped
# Channels per model; "mini" is a Mini Maestro of unstated size (any of 12, 18, 24).
MODELS = {"micro": 6, "mini12": 12, "mini18": 18, "mini24": 24, "mini": 24}
MODEL_NAMES = {"micro": "Micro Maestro 6", "mini12": "Mini Maestro 12",
               "mini18": "Mini Maestro 18", "mini24": "Mini Maestro 24", "mini": "Mini Maestro"}

Protocol = Literal["compact", "pololu"]

# Bit numbers of the Get Errors reply, as the user's guide lists them.
ERROR_BITS = (
    "serial signal error",
    "serial overrun error",
    "serial buffer full",
    "serial CRC error",
    "serial protocol error",
    "serial timeout error",
    "script stack error",
    "script call stack error",
    "script program counter error",
)


def _frame(command: int, data: bytes, protocol: Protocol, device: int) -> bytes:
    if protocol == "compact":
        return bytes([command]) + data
    if protocol == "pololu":
        if not 0 <= device <= 127:
            raise ValueError(f"Maestro device number must be 0..127, got {device}")
        return bytes([POLOLU_START, device, command & 0x7F]) + data
    raise ValueError(f"unknown Maestro protocol {protocol!r} (compact or pololu)")


def n_channels(model: str | None) -> int:
    """Channels of a Maestro model (None: any Maestro, so up to the Mini Maestro 24's)."""
    if model is None:
        return MAX_CHANNELS
    if model not in MODELS:
        raise ArgumentError(f"unknown Maestro model {model!r} (choose from {', '.join(MODELS)})")
    return MODELS[model]


def describe_model(model: str | None) -> str:
    return "a Maestro" if model is None else f"a {MODEL_NAMES[model]}"


def _channel(channel: int) -> int:
    if not 0 <= channel < MAX_CHANNELS:
        raise ValueError(f"Maestro channel must be 0..{MAX_CHANNELS - 1}, got {channel}")
    return channel


def _seven_bit_pair(value: int, what: str) -> bytes:
    if not 0 <= value <= MAX_14BIT:
        raise ValueError(f"Maestro {what} must be 0..{MAX_14BIT}, got {value}")
    return bytes([value & 0x7F, (value >> 7) & 0x7F])


def quarter_us(pulse_us: float) -> int:
    """Pulse width in the Maestro's unit (quarter-microseconds), rounded to the nearest."""
    return int(round(float(pulse_us) * 4))


def set_target(channel: int, target_qus: int, protocol: Protocol = "compact",
               device: int = DEFAULT_DEVICE) -> bytes:
    """Set Target; ``target_qus`` in quarter-microseconds (0 switches the pulses off)."""
    data = bytes([_channel(channel)]) + _seven_bit_pair(target_qus, "target")
    return _frame(SET_TARGET, data, protocol, device)


def set_speed(channel: int, speed: int, protocol: Protocol = "compact",
              device: int = DEFAULT_DEVICE) -> bytes:
    """Set Speed in units of 0.25 us / 10 ms (0 = unlimited)."""
    data = bytes([_channel(channel)]) + _seven_bit_pair(speed, "speed")
    return _frame(SET_SPEED, data, protocol, device)


def set_acceleration(channel: int, acceleration: int, protocol: Protocol = "compact",
                     device: int = DEFAULT_DEVICE) -> bytes:
    """Set Acceleration in units of 0.25 us / 10 ms / 80 ms (0 = unlimited, max 255)."""
    if not 0 <= acceleration <= 255:
        raise ValueError(f"Maestro acceleration must be 0..255, got {acceleration}")
    data = bytes([_channel(channel)]) + _seven_bit_pair(acceleration, "acceleration")
    return _frame(SET_ACCELERATION, data, protocol, device)


def get_position(channel: int, protocol: Protocol = "compact",
                 device: int = DEFAULT_DEVICE) -> bytes:
    return _frame(GET_POSITION, bytes([_channel(channel)]), protocol, device)


def get_moving_state(protocol: Protocol = "compact", device: int = DEFAULT_DEVICE) -> bytes:
    return _frame(GET_MOVING_STATE, b"", protocol, device)


def get_errors(protocol: Protocol = "compact", device: int = DEFAULT_DEVICE) -> bytes:
    return _frame(GET_ERRORS, b"", protocol, device)


def go_home(protocol: Protocol = "compact", device: int = DEFAULT_DEVICE) -> bytes:
    return _frame(GO_HOME, b"", protocol, device)


def decode_u16(reply: bytes) -> int:
    """A two-byte reply (Get Position, Get Errors): low byte first, full 8-bit bytes."""
    if len(reply) != 2:
        raise ValueError(f"expected a two-byte reply, got {reply.hex(' ') or 'nothing'}")
    return reply[0] | (reply[1] << 8)


def decode_errors(bits: int) -> list[str]:
    names = [name for i, name in enumerate(ERROR_BITS) if bits & (1 << i)]
    names += [f"error bit {i}" for i in range(len(ERROR_BITS), 16) if bits & (1 << i)]
    return names


def speed_units(speed_us_per_s: float) -> int:
    """us/s to the Maestro's 0.25 us per 10 ms (= 25 us/s per unit); at least 1."""
    return max(1, min(MAX_14BIT, int(round(speed_us_per_s / 25.0))))


class Maestro(ServoController):
    """A Pololu Maestro on a serial port ("Command Port" in USB Dual Port mode, or TTL).

    Settling watches the read-back, not Get Moving State (see the module doc): a move is done
    when Get Position reads back every target to the quarter-microsecond.
    """

    resolution_us = 0.25
    readback_tolerance_us = 0.0  # Get Position reports the exact quarter-microsecond output
    moving_state_reliable = False  # the Micro Maestro's Get Moving State can miss a ramp

    def __init__(self, *args, protocol: Protocol = "compact", device: int = DEFAULT_DEVICE,
                 acceleration: int | None = None, model: str | None = None,
                 auto_baud: bool = False, **kwargs):
        super().__init__(*args, **kwargs)
        if protocol not in ("compact", "pololu"):
            raise ValueError(f"unknown Maestro protocol {protocol!r} (compact or pololu)")
        self.wire_protocol: Protocol = protocol
        self.device = device
        self.acceleration = acceleration
        self.model = model
        self.auto_baud = auto_baud
        self.protocol = f"maestro ({protocol} protocol)"
        limit = n_channels(model)
        for arm, chs in self.channels.items():
            for ch in chs:
                _channel(ch)  # fail before the port is touched
                if ch >= limit:
                    raise ArgumentError(f"channel {ch} of arm {arm!r} does not exist "
                                        f"({describe_model(model)} has channels 0..{limit - 1})")

    def connect(self) -> str:
        baud_byte = self.auto_baud and self.wire_protocol == "compact"
        if baud_byte:
            self.link.write(bytes([BAUD_INDICATION]))
            self._sleep(0.01)  # the Maestro times that byte's bits before it decodes more
        # Get Errors both proves the device answers and clears stale flags from before us.
        try:
            errs = self.errors()
        except HardwareError as exc:
            hint = ("" if self.auto_baud else "; if its serial mode is 'UART, detect baud rate', "
                    "pass --auto-baud")
            raise HardwareError(f"no answer from a Maestro on {self.link.name} ({exc}); check "
                                "the port (use the Command Port), --baud, --device-number and "
                                f"that the serial mode is USB Dual Port or UART{hint}") from None
        if baud_byte:
            # A Maestro that was not waiting for a baud rate read our lone 0xAA as a Pololu
            # command cut short: that protocol error is ours, not the device's.
            errs = [e for e in errs if e != "serial protocol error"]
        for ch in (c for chs in self.channels.values() for c in chs):
            if self.speed_us_per_s:
                self.link.write(set_speed(ch, speed_units(self.speed_us_per_s),
                                          self.wire_protocol, self.device))
            if self.acceleration is not None:
                self.link.write(set_acceleration(ch, self.acceleration, self.wire_protocol,
                                                 self.device))
        note = f"; cleared earlier errors: {', '.join(errs)}" if errs else ""
        model = f"{MODEL_NAMES[self.model]} " if self.model else "Maestro "
        return f"{model}on {self.link.name} ({self.wire_protocol} protocol){note}"

    def stuck_error(self, pos: Mapping[str, tuple[float, float]],
                    commands: Mapping[str, tuple[float, float]]) -> HardwareError:
        short = self._short(pos, commands)
        where = "; ".join(f"channel {ch} (arm {a!r} joint {j}) was commanded {c:g} us but stays "
                          f"at {p:g} us" for a, j, ch, c, p in short)
        lo, hi = FACTORY_RANGE_US
        return HardwareError(
            f"{self.protocol}: {where}: the channel's range clamps the target; widen its Min "
            f"and Max in the Maestro Control Center (Channel Settings tab, factory {lo:g}-{hi:g} "
            "us) to cover the rig's pulse_limits, then Apply Settings")

    def _send_move(self, moves: list[tuple[int, float]]) -> None:
        # All targets in one write: the channels start their ramps together.
        data = b"".join(set_target(ch, quarter_us(u), self.wire_protocol, self.device)
                        for ch, u in moves)
        self.link.write(data)

    def is_moving(self) -> bool:
        """Get Moving State: a 1 is reliable, a 0 on a Micro Maestro may be wrong."""
        reply = self.query(get_moving_state(self.wire_protocol, self.device), 1,
                           "Get Moving State", valid=lambda r: r[0] in (0, 1))
        return reply[0] == 1

    def channel_position(self, channel: int) -> float:
        reply = self.query(get_position(channel, self.wire_protocol, self.device), 2,
                           f"Get Position (channel {channel})",
                           valid=lambda r: decode_u16(r) <= MAX_14BIT)
        return decode_u16(reply) / 4.0

    def errors(self) -> list[str]:
        reply = self.query(get_errors(self.wire_protocol, self.device), 2, "Get Errors")
        return decode_errors(decode_u16(reply))

    def home(self) -> None:
        """Go Home: every channel to its configured home position (or off)."""
        self.link.write(go_home(self.wire_protocol, self.device))
