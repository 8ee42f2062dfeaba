"""Lynxmotion SSC-32 and SSC-32U servo controllers over their ASCII command set.

Commands (each ends with a carriage return):

- ``#<ch>P<pw>[S<spd>]...[T<ms>]`` moves one or more channels; several ``#..P..`` in one
  command form a group move that starts (and, with ``T``, ends) together. ``pw`` is the pulse
  width in microseconds (500..2500), ``S`` a per-channel speed in us per second, ``T`` the
  time in ms for the whole group.
- ``Q`` asks whether the previous move is done: one byte, ``.`` done or ``+`` still moving.
- ``QP<ch>`` asks for a channel's pulse width: one byte, pulse width / 10 (so 150 = 1500 us).
- ``VER`` returns the firmware version text, e.g. ``SSC32-V2.50USB``.

The SSC-32 commands whole microseconds and reports back in steps of 10 us, so its read-back
confirms a move to within 10 us, not exactly as the Maestro's does.
"""

from __future__ import annotations

from collections.abc import Sequence

from bayesrob.hardware.controller import Commands, HardwareError, LimitError, ServoController

MAX_CHANNELS = 32
PULSE_RANGE_US = (500, 2500)


def _channel(channel: int) -> int:
    if not 0 <= channel < MAX_CHANNELS:
        raise ValueError(f"SSC-32 channel must be 0..{MAX_CHANNELS - 1}, got {channel}")
    return channel


def move_command(moves: Sequence[tuple[int, float]], speed_us_per_s: float | None = None,
                 time_ms: int | None = None) -> bytes:
    """A (group) move: ``#0P1500S500#1P1600S500T1000\\r``."""
    if not moves:
        raise ValueError("a move needs at least one channel")
    parts = []
    for ch, pw in moves:
        p = int(round(float(pw)))
        if not PULSE_RANGE_US[0] <= p <= PULSE_RANGE_US[1]:
            raise ValueError(f"SSC-32 pulse width must be {PULSE_RANGE_US[0]}.."
                             f"{PULSE_RANGE_US[1]} us, got {pw}")
        part = f"#{_channel(ch)}P{p}"
        if speed_us_per_s:
            part += f"S{max(1, int(round(speed_us_per_s)))}"
        parts.append(part)
    if time_ms is not None:
        if time_ms < 0:
            raise ValueError(f"move time must be >= 0 ms, got {time_ms}")
        parts.append(f"T{int(time_ms)}")
    return ("".join(parts) + "\r").encode("ascii")


def query_movement() -> bytes:
    return b"Q\r"


def query_pulse(channel: int) -> bytes:
    return f"QP{_channel(channel)}\r".encode("ascii")


def version() -> bytes:
    return b"VER\r"


class SSC32(ServoController):
    """A Lynxmotion SSC-32 / SSC-32U."""

    protocol = "ssc32"
    resolution_us = 1.0
    readback_tolerance_us = 10.0  # QP answers in tens of microseconds

    def __init__(self, *args, time_ms: int | None = None, **kwargs):
        super().__init__(*args, **kwargs)
        self.time_ms = time_ms
        for chs in self.channels.values():
            for ch in chs:
                _channel(ch)

    def check(self, commands: Commands) -> dict[str, tuple[float, float]]:
        checked = super().check(commands)
        lo, hi = PULSE_RANGE_US
        for arm, pair in checked.items():
            for p in pair:
                if not lo <= p <= hi:
                    raise LimitError(f"arm {arm!r}: pulse {p:g} us is outside the SSC-32's "
                                     f"range [{lo}, {hi}]; nothing was sent")
        return checked

    def connect(self) -> str:
        last: Exception | None = None
        for _ in range(self.retries):
            self.link.discard_input()
            self.link.write(version())
            try:
                text = self.link.read_until(b"\r", "VER").decode("ascii", "replace").strip()
            except HardwareError as exc:
                last = exc
                continue
            if text.upper().startswith("SSC"):
                return f"{text} on {self.link.name}"
            last = HardwareError(f"VER answered {text!r}")
        raise HardwareError(f"no answer from an SSC-32 on {self.link.name} ({last}); check the "
                            "port and --baud (the SSC-32U's baud LED/button setting)")

    def _send_move(self, moves: list[tuple[int, float]]) -> None:
        self.link.write(move_command(moves, self.speed_us_per_s, self.time_ms))

    def is_moving(self) -> bool:
        reply = self.query(query_movement(), 1, "Q", valid=lambda r: r in (b".", b"+"))
        return reply == b"+"

    def channel_position(self, channel: int) -> float:
        reply = self.query(query_pulse(channel), 1, f"QP{channel}",
                           valid=lambda r: PULSE_RANGE_US[0] // 10 <= r[0]
                           <= PULSE_RANGE_US[1] // 10)
        return reply[0] * 10.0
