"""A simulated rig on pseudo-terminals: a servo controller and a tracker, without hardware.

:class:`SimDevice` opens two pseudo-terminals (``os.openpty``, raw mode). On the servo port it
answers like a Pololu Maestro (compact and Pololu protocol at once, as the real one does) or a
Lynxmotion SSC-32; on the tracker port it streams ``$PXYT`` (or plain ``x,y``) lines of the end
point. End points come from :class:`bayesrob.sim.PhysicalRig`: the pulses the controller
received drive the simulated arms, with gravity, backlash and the rest of the truth's effects.

When a move is over. The device cannot see a person, so it settles the arms when the host first
queries it after new targets (Get Moving State, Get Position, Get Errors; ``Q``, ``QP``,
``VER``), which every move of ``bayesrob collect`` does. The arms it settles are those that got
new targets since the last settle, and the tracker follows them.

Linking (``linked``):

- ``auto`` (default): arms count as linked when one move commands more than one arm, which is
  what ``collect`` does only after the operator confirmed linking; a move of one arm frees it.
- ``always``: every move settles all arms linked at their end points.
- ``never``: arms are always free; the tracker follows the first arm (rig order) of the move.

Faults, for testing what the host survives: bytes the device sends dropped (``drop_rate``) or
replaced (``garble_rate``), bytes it receives on the servo port corrupted (``rx_garble_rate``),
tracker lines with a wrong checksum (``bad_checksum_rate``) or a wild reading 5 to 50 mm off
with a good checksum, as a reflection gives (``outlier_rate``), servo replies delayed
(``reply_delay_s``), the servo port closed after ``disconnect_after`` commands, as when a
USB cable is pulled, and a serial error flagged after ``error_after`` commands (once), as line
noise would. Every byte received on the servo port is kept (``received``) and, with
``byte_log``, appended to a file.

A real Maestro's quirks, each off unless asked for (see :mod:`bayesrob.hardware.maestro`):

- ``moving_state_bug``: Get Moving State answers 0 even while outputs ramp (Micro Maestro 6).
- ``channel_range=(lo, hi)``: every target is clamped to it, as each channel's Min and Max do
  (:data:`~bayesrob.hardware.maestro.FACTORY_RANGE_US` as shipped).
- ``on_error``: what every output does when an error is flagged (a protocol error from a
  garbled byte, the ``error_after`` fault, :meth:`SimDevice.inject_error`): ``ignore`` (keep
  its target), ``off`` (no pulses, the factory setting: the arm goes limp) or ``home`` (its
  home pulse, the arm's mid-range).
- ``serial_mode="uart-detect"``: nothing is decoded until a 0xAA baud rate indication byte.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import re
import select
import sys
import threading
import time
import tty
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import numpy as np

from bayesrob.hardware import maestro as mae
from bayesrob.hardware.controller import ArgumentError
from bayesrob.hardware.tracker import FORMATS, format_plain, format_pxyt

LINK_MODES = ("auto", "always", "never")
SSC32_VERSION = b"SSC32-V2.50USB\r"
PROTOCOL_ERROR_BIT = 1 << 4  # "serial protocol error" in the Maestro's Get Errors reply
SIGNAL_ERROR_BIT = 1 << 0  # "serial signal error": what noise on the line flags
ON_ERROR = ("ignore", "off", "home")
SERIAL_MODES = ("usb", "uart-detect")
_MAESTRO_DATA = {mae.SET_TARGET: 3, mae.SET_SPEED: 3, mae.SET_ACCELERATION: 3,
                 mae.GET_POSITION: 1, mae.GET_MOVING_STATE: 0, mae.GET_ERRORS: 0,
                 mae.GO_HOME: 0}
_MAESTRO_QUERIES = (mae.GET_POSITION, mae.GET_MOVING_STATE, mae.GET_ERRORS)
_SSC32_MOVE = re.compile(r"((?:#\d+P\d+(?:S\d+)?)+)(?:T(\d+))?")
_SSC32_PART = re.compile(r"#(\d+)P(\d+)(?:S(\d+))?")


@dataclass(frozen=True)
class Faults:
    drop_rate: float = 0.0
    garble_rate: float = 0.0
    rx_garble_rate: float = 0.0
    bad_checksum_rate: float = 0.0
    reply_delay_s: float = 0.0
    disconnect_after: int | None = None
    error_after: int | None = None
    outlier_rate: float = 0.0

    def __post_init__(self) -> None:
        for name in ("drop_rate", "garble_rate", "rx_garble_rate", "bad_checksum_rate",
                     "outlier_rate"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{name} must be between 0 and 1, got {v}")
        if self.reply_delay_s < 0:
            raise ValueError(f"reply_delay_s must be >= 0, got {self.reply_delay_s}")
        for name in ("disconnect_after", "error_after"):
            if getattr(self, name) is not None and getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")


# ------------------------------------------------------------------------------ decoders


class MaestroDecoder:
    """Bytes in, complete Maestro commands out, resynchronising as the real one does.

    A byte with its MSB set always starts a command; a data byte where a command should start,
    or a command byte where data should be, is a protocol error (bit 4 of Get Errors).
    Pololu-protocol commands for another device number are read and ignored.
    """

    def __init__(self, device: int = mae.DEFAULT_DEVICE):
        self.device = device
        self.buf = bytearray()
        self.errors = 0
        # The next 0xAA is a baud rate indication: followed by a command byte it is consumed
        # silently; followed by a data byte it also starts a Pololu-protocol command.
        self.baud_byte = False

    def _error(self, n_drop: int) -> None:
        self.errors |= PROTOCOL_ERROR_BIT
        del self.buf[:max(1, n_drop)]

    def feed(self, data: bytes) -> list[tuple[int, bytes]]:
        """(compact command byte, data bytes) for each complete command addressed to us."""
        self.buf += data
        out: list[tuple[int, bytes]] = []
        buf = self.buf
        while buf:
            first = buf[0]
            if first < 0x80:
                self._error(1)
                continue
            device = None
            if self.baud_byte and first == mae.BAUD_INDICATION:
                if len(buf) < 2:
                    break
                self.baud_byte = False
                if buf[1] >= 0x80:
                    del buf[:1]
                    continue
            if first == mae.POLOLU_START:
                if len(buf) < 3:
                    if len(buf) == 2 and buf[1] >= 0x80:
                        self._error(1)
                        continue
                    break
                if buf[1] >= 0x80:
                    self._error(1)
                    continue
                if buf[2] >= 0x80:
                    self._error(2)
                    continue
                device, command, head = buf[1], buf[2] | 0x80, 3
            else:
                command, head = first, 1
            if command == mae.SET_MULTIPLE_TARGETS:
                if len(buf) < head + 1:
                    break
                if buf[head] >= 0x80:
                    self._error(head)
                    continue
                n = 2 + 2 * buf[head]
            elif command in _MAESTRO_DATA:
                n = _MAESTRO_DATA[command]
            else:
                self._error(head)
                continue
            payload = buf[head:head + n]
            bad = next((i for i, b in enumerate(payload) if b >= 0x80), None)
            if bad is not None:
                self._error(head + bad)  # the byte with its MSB set starts the next command
                continue
            if len(payload) < n:
                break
            del buf[:head + n]
            if device is None or device == self.device:
                out.append((command, bytes(payload)))
        return out


class SSC32Decoder:
    """Bytes in, command lines out (terminated by carriage return)."""

    MAX_LINE = 512

    def __init__(self) -> None:
        self.buf = bytearray()

    def feed(self, data: bytes) -> list[str]:
        self.buf += data
        lines = []
        while b"\r" in self.buf:
            line, _, rest = bytes(self.buf).partition(b"\r")
            self.buf = bytearray(rest)
            lines.append(line.decode("ascii", "replace"))
        if len(self.buf) > self.MAX_LINE:
            self.buf.clear()  # a runaway line without terminator: the real board drops it too
        return lines


def parse_ssc32(line: str) -> tuple | None:
    """One command line to ('move', [(ch, pw, speed)], time_ms), ('Q',), ('QP', [chs]),
    ('VER',), or None for anything the device ignores."""
    text = line.replace(" ", "").replace("\n", "").upper()
    if text == "VER":
        return ("VER",)
    if text == "Q":
        return ("Q",)
    if text.startswith("QP"):
        parts = text.split("QP")[1:]
        if parts and all(p.isdigit() for p in parts):
            return ("QP", [int(p) for p in parts])
        return None
    m = _SSC32_MOVE.fullmatch(text)
    if not m:
        return None
    moves = [(int(c), int(p), int(s) if s else None) for c, p, s in _SSC32_PART.findall(m[1])]
    return ("move", moves, int(m[2]) if m[2] else None)


def parse_channel_range(text: str) -> tuple[float, float]:
    """``--channel-range``: ``MIN,MAX`` in us, or ``factory`` for a Maestro as shipped."""
    if text.strip().lower() == "factory":
        return mae.FACTORY_RANGE_US
    parts = text.split(",")
    try:
        lo, hi = (float(p) for p in parts)
    except ValueError:
        raise ArgumentError(f"--channel-range: expected MIN,MAX in us or 'factory', got "
                            f"{text!r}") from None
    if not 0 < lo < hi:
        raise ArgumentError(f"--channel-range: need 0 < MIN < MAX, got {text!r}")
    return lo, hi


# ------------------------------------------------------------------------------ the device


@dataclass
class _Output:
    """One servo output ramping linearly from ``start_us`` to ``target_us``."""

    target_us: float
    start_us: float = 0.0
    t0: float = 0.0
    t1: float = 0.0
    speed: int = 0  # Maestro units (0.25 us / 10 ms); 0 = unlimited

    def __post_init__(self) -> None:
        self.start_us = self.target_us

    def position(self, now: float) -> float:
        if now >= self.t1 or self.t1 <= self.t0:
            return self.target_us
        frac = (now - self.t0) / (self.t1 - self.t0)
        return self.start_us + (self.target_us - self.start_us) * max(0.0, frac)

    def ramp_s(self, target_us: float, now: float) -> float:
        """How long a ramp to ``target_us`` takes at the speed limit. From "off" there is no
        position to ramp from: the output starts at its target."""
        pos = self.position(now)
        return abs(target_us - pos) / (25.0 * self.speed) if self.speed and pos > 0 else 0.0

    def go(self, target_us: float, now: float, duration_s: float) -> None:
        self.start_us = self.position(now)
        self.target_us = target_us
        self.t0, self.t1 = now, now + max(0.0, duration_s)


@dataclass
class Pose:
    """A settle: which arms (linked if several), their pulses, the true-plus-noise end point."""

    arms: tuple[str, ...]
    commands: dict[str, tuple[float, float]]
    end_point: np.ndarray = field(repr=False)


def _nonblocking(fd: int) -> None:
    fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) | os.O_NONBLOCK)


class SimDevice:
    """The simulated controller and tracker, served on two pseudo-terminals from threads."""

    def __init__(self, plant, protocol: str = "maestro", *,
                 channels: Mapping[str, Sequence[int]] | None = None,
                 device_number: int = mae.DEFAULT_DEVICE, linked: str = "auto",
                 tracker_format: str = "pxyt", tracker_rate_hz: float = 100.0,
                 tracker_noise_mm: float = 0.02, faults: Faults | None = None, seed: int = 0,
                 byte_log: str | Path | None = None, moving_state_bug: bool = False,
                 channel_range: tuple[float, float] | None = None, on_error: str = "ignore",
                 serial_mode: str = "usb"):
        if protocol not in ("maestro", "ssc32"):
            raise ValueError(f"unknown protocol {protocol!r} (maestro or ssc32)")
        if on_error not in ON_ERROR:
            raise ValueError(f"on_error must be one of {', '.join(ON_ERROR)}, got {on_error!r}")
        if serial_mode not in SERIAL_MODES:
            raise ValueError(f"serial_mode must be one of {', '.join(SERIAL_MODES)}, got "
                             f"{serial_mode!r}")
        if channel_range is not None and not 0 < channel_range[0] < channel_range[1]:
            raise ArgumentError(f"channel range must be MIN,MAX with 0 < MIN < MAX, got "
                                f"{channel_range}")
        if linked not in LINK_MODES:
            raise ValueError(f"linked must be one of {', '.join(LINK_MODES)}, got {linked!r}")
        if tracker_format not in FORMATS:
            raise ValueError(f"tracker format must be one of {', '.join(FORMATS)}")
        if tracker_rate_hz <= 0:
            raise ValueError(f"tracker rate must be positive, got {tracker_rate_hz}")
        self.plant = plant
        self.truth = plant.truth
        self.arm_names = list(self.truth.arms)
        if channels is None:
            channels = {a: (2 * i, 2 * i + 1) for i, a in enumerate(self.arm_names)}
        unknown = set(channels) - set(self.arm_names)
        if unknown:
            raise ArgumentError(f"channels name unknown arm(s) {sorted(unknown)}; the truth has "
                             f"{', '.join(self.arm_names)}")
        self.channels = {a: (int(c[0]), int(c[1])) for a, c in channels.items()}
        self.protocol = protocol
        self.linked = linked
        self.tracker_format = tracker_format
        self.tracker_period_s = 1.0 / tracker_rate_hz
        self.tracker_noise_mm = tracker_noise_mm
        self.faults = faults or Faults()
        self.byte_log = Path(byte_log) if byte_log else None
        self.moving_state_bug = moving_state_bug
        self.channel_range = None if channel_range is None else (float(channel_range[0]),
                                                                 float(channel_range[1]))
        self.on_error = on_error
        self.baud_detected = serial_mode == "usb" or protocol != "maestro"
        self.errors_raised = 0  # errors flagged by the device (each applied on_error)
        self.false_idle_answers = 0  # Get Moving State answered 0 while outputs moved (bug)
        self.outliers_sent = 0
        self._maestro = MaestroDecoder(device_number)
        self._ssc32 = SSC32Decoder()
        self._tx_rng = np.random.default_rng([seed, 1])
        self._rx_rng = np.random.default_rng([seed, 2])
        self._tracker_rng = np.random.default_rng([seed, 3])
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._received = bytearray()
        self._log_fh = None
        self._fds: dict[str, tuple[int, int]] = {}
        self.servo_port = ""
        self.tracker_port = ""
        self.commands_handled = 0
        self.corrupted_replies = 0  # controller replies dropped into or garbled by the faults
        self.disconnected = False
        self.poses: list[Pose] = []
        self._moved: list[str] = []
        self._outputs: dict[int, _Output] = {}
        for name in self.arm_names:
            arm = self.truth.arms[name]
            for ch, u in zip(self.channels.get(name, ()), arm.u_mid, strict=False):
                self._outputs[ch] = _Output(float(u))
        self.home_us = {ch: o.target_us for ch, o in self._outputs.items()}
        self._end_point: np.ndarray | None = None

    # -- life cycle ------------------------------------------------------------------------
    def start(self) -> SimDevice:
        """Warm the physics up (the first solve compiles), open the ports, start serving."""
        first = self.arm_names[0]
        home = {a: self._pulses(a) for a in self.arm_names if a in self.channels}
        for a, u in home.items():
            d = self.plant.end_point({a: u}, noise=False)
            if a == first:
                self._end_point = np.asarray(d)
        if len(home) > 1:
            self.plant.end_point(home, noise=False)
        if self.byte_log is not None:
            self._log_fh = self.byte_log.open("ab")
        for role in ("servo", "tracker"):
            master, slave = os.openpty()
            tty.setraw(slave)
            _nonblocking(master)
            # Keeping our copy of the slave open keeps the terminal alive between clients.
            self._fds[role] = (master, slave)
        self.servo_port = os.ttyname(self._fds["servo"][1])
        self.tracker_port = os.ttyname(self._fds["tracker"][1])
        for target in (self._serve_servo, self._serve_tracker):
            t = threading.Thread(target=target, daemon=True, name=f"simdevice-{target.__name__}")
            t.start()
            self._threads.append(t)
        return self

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=5)
        self._threads.clear()
        for role in list(self._fds):
            self._close(role)
        if self._log_fh is not None:
            self._log_fh.close()
            self._log_fh = None

    def __enter__(self) -> SimDevice:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def wait(self) -> None:
        """Block until :meth:`stop` (from a signal handler or another thread)."""
        while not self._stop.wait(0.2):
            pass

    def _close(self, role: str) -> None:
        fds = self._fds.pop(role, None)
        for fd in fds or ():
            with contextlib.suppress(OSError):
                os.close(fd)

    @property
    def received(self) -> bytes:
        """Every byte received on the servo port so far."""
        with self._lock:
            return bytes(self._received)

    @property
    def end_point(self) -> np.ndarray | None:
        with self._lock:
            return None if self._end_point is None else self._end_point.copy()

    # -- state -------------------------------------------------------------------------------
    def _pulses(self, arm: str) -> tuple[float, float]:
        c1, c2 = self.channels[arm]
        return self._outputs[c1].target_us, self._outputs[c2].target_us

    def _arm_of(self, channel: int) -> str | None:
        return next((a for a, chs in self.channels.items() if channel in chs), None)

    def _set_target(self, channel: int, us: float, duration_s: float) -> None:
        out = self._outputs.setdefault(channel, _Output(us))
        out.go(us, time.monotonic(), duration_s)
        arm = self._arm_of(channel)
        if arm is not None and arm not in self._moved:
            self._moved.append(arm)

    def _moving(self) -> bool:
        now = time.monotonic()
        return any(now < o.t1 for o in self._outputs.values())

    def _settle(self, only: Sequence[str] | None = None) -> None:
        """The arms moved since the last settle (or ``only`` these) come to rest; the tracker
        now sees them."""
        if not self._moved:
            return
        moved = [a for a in self.arm_names if a in self._moved]
        self._moved = []
        if only is not None:
            arms = list(only)
        elif self.linked == "always":
            arms = [a for a in self.arm_names if a in self.channels]
        elif self.linked == "never":
            arms = moved[:1]
        else:
            arms = moved
        commands = {a: self._pulses(a) for a in arms}
        if any(u <= 0 for pair in commands.values() for u in pair):
            return  # an output switched off: the arm hangs limp and the tracker keeps its last
        d = np.asarray(self.plant.end_point(commands), float)
        with self._lock:
            self._end_point = d
            self.poses.append(Pose(tuple(arms), commands, d))

    def inject_error(self, bits: int = SIGNAL_ERROR_BIT) -> None:
        """Flag an error as the controller would on line noise, and apply ``on_error``."""
        self._maestro.errors |= bits
        self._apply_on_error()

    def _apply_on_error(self) -> None:
        self.errors_raised += 1
        if self.on_error == "ignore" or self.protocol != "maestro":
            return
        now = time.monotonic()
        for ch, out in self._outputs.items():
            if self.on_error == "off":
                self._set_target(ch, 0.0, 0.0)
            else:
                # With a speed limit the output ramps to its home, as the user's guide says.
                home = self.home_us.get(ch, out.target_us)
                self._set_target(ch, home, out.ramp_s(home, now))
        # The tracker keeps watching the arms it watched; they now hang limp or at home.
        watched = self.poses[-1].arms if self.poses else None
        self._settle(watched)

    def _detect_baud(self, data: bytes) -> bytes:
        """In 'UART, detect baud rate' mode, drop everything before the first 0xAA."""
        if self.baud_detected:
            return data
        i = data.find(bytes([mae.BAUD_INDICATION]))
        if i < 0:
            return b""
        self.baud_detected = True
        self._maestro.baud_byte = True
        return data[i:]

    # -- servo port --------------------------------------------------------------------------
    def _serve_servo(self) -> None:
        master = self._fds["servo"][0]
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([master], [], [], 0.05)
                if not ready:
                    continue
                data = os.read(master, 4096)
            except BlockingIOError:
                continue
            except OSError:
                time.sleep(0.05)  # no client on the other side right now
                continue
            if not data:
                continue
            with self._lock:
                self._received += data
            if self._log_fh is not None:
                self._log_fh.write(data)
                self._log_fh.flush()
            data = self._corrupt(data, self._rx_rng, 0.0, self.faults.rx_garble_rate)
            if self.protocol == "maestro":
                before = self._maestro.errors
                commands = [("m", c) for c in self._maestro.feed(self._detect_baud(data))]
                if self._maestro.errors & ~before:
                    self._apply_on_error()
            else:
                commands = [("s", c) for c in self._ssc32.feed(data)]
            for kind, cmd in commands:
                try:
                    reply = (self._maestro_command(*cmd) if kind == "m"
                             else self._ssc32_command(cmd))
                except (IndexError, ValueError, KeyError):
                    # A command the decoder let through but cannot be carried out: a real
                    # controller flags it and keeps serving, and so do we.
                    self.inject_error(PROTOCOL_ERROR_BIT)
                    reply = b""
                if reply:
                    self._reply(master, reply)
                self.commands_handled += 1
                if self.commands_handled == self.faults.error_after:
                    self.inject_error()
                k = self.faults.disconnect_after
                if k is not None and self.commands_handled >= k:
                    self.disconnected = True
                    self._close("servo")
                    return

    def _reply(self, master: int, reply: bytes) -> None:
        if self.faults.reply_delay_s:
            time.sleep(self.faults.reply_delay_s)
        data = self._corrupt(reply, self._tx_rng, self.faults.drop_rate, self.faults.garble_rate)
        if data != reply:
            self.corrupted_replies += 1
        self._write(master, data)

    @staticmethod
    def _write(fd: int, data: bytes) -> None:
        # nobody reading and the buffer full: a UART would overrun the same way
        with contextlib.suppress(OSError):
            os.write(fd, data)

    @staticmethod
    def _corrupt(data: bytes, rng: np.random.Generator, drop: float, garble: float) -> bytes:
        if not data or (drop == 0 and garble == 0):
            return data
        arr = np.frombuffer(data, np.uint8).copy()
        hit = rng.random(len(arr)) < garble
        if hit.any():
            # A garbled byte is always a different byte.
            arr[hit] = (arr[hit] + rng.integers(1, 256, hit.sum())).astype(np.uint8)
        keep = rng.random(len(arr)) >= drop
        return arr[keep].tobytes()

    def _maestro_command(self, command: int, data: bytes) -> bytes:
        if command in _MAESTRO_QUERIES:
            self._settle()
        if command == mae.SET_TARGET:
            ch, target_q = data[0], data[1] | (data[2] << 7)
            us = target_q / 4
            if self.channel_range is not None and us > 0:
                us = min(max(us, self.channel_range[0]), self.channel_range[1])
            out = self._outputs.get(ch)
            self._set_target(ch, us, out.ramp_s(us, time.monotonic()) if out else 0.0)
        elif command == mae.SET_MULTIPLE_TARGETS:
            n, first = data[0], data[1]
            for i in range(n):
                lo, hi = data[2 + 2 * i], data[3 + 2 * i]
                self._maestro_command(mae.SET_TARGET, bytes([first + i, lo, hi]))
        elif command == mae.SET_SPEED:
            self._outputs.setdefault(data[0], _Output(0.0)).speed = data[1] | (data[2] << 7)
        elif command == mae.SET_ACCELERATION:
            pass  # ramps are linear here; acceleration only shapes them
        elif command == mae.GET_POSITION:
            out = self._outputs.get(data[0])
            q = int(round(out.position(time.monotonic()) * 4)) if out else 0
            return bytes([q & 0xFF, (q >> 8) & 0xFF])
        elif command == mae.GET_MOVING_STATE:
            moving = self._moving()
            if moving and self.moving_state_bug:
                self.false_idle_answers += 1
                return b"\x00"
            return b"\x01" if moving else b"\x00"
        elif command == mae.GET_ERRORS:
            bits, self._maestro.errors = self._maestro.errors, 0
            return bytes([bits & 0xFF, (bits >> 8) & 0xFF])
        elif command == mae.GO_HOME:
            for ch, us in self.home_us.items():
                self._set_target(ch, us, 0.0)
        return b""

    def _ssc32_command(self, line: str) -> bytes:
        cmd = parse_ssc32(line)
        if cmd is None:
            return b""
        if cmd[0] != "move":
            self._settle()
        if cmd[0] == "VER":
            return SSC32_VERSION
        if cmd[0] == "Q":
            return b"+" if self._moving() else b"."
        if cmd[0] == "QP":
            now = time.monotonic()
            return bytes(int(round(self._outputs[c].position(now) / 10)) if c in self._outputs
                         else 0 for c in cmd[1])
        _, moves, time_ms = cmd
        if any(not 500 <= pw <= 2500 or ch > 31 for ch, pw, _ in moves):
            return b""  # the board ignores a command it cannot carry out
        now = time.monotonic()
        durations = []
        for ch, pw, speed in moves:
            out = self._outputs.get(ch)
            start = out.position(now) if out else pw
            durations.append(abs(pw - start) / speed if speed else 0.0)
        # A group move ends together: at its T, or when its slowest channel arrives.
        group = max(durations + [time_ms / 1000 if time_ms else 0.0])
        for ch, pw, _ in moves:
            self._set_target(ch, float(pw), group)
        return b""

    # -- tracker port ------------------------------------------------------------------------
    def _serve_tracker(self) -> None:
        master = self._fds["tracker"][0]
        next_t = time.monotonic()
        while not self._stop.is_set():
            next_t += self.tracker_period_s
            delay = next_t - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            else:
                next_t = time.monotonic()
            with contextlib.suppress(OSError):
                os.read(master, 4096)  # a tracker does not listen; drain what a host sent
            d = self.end_point
            if d is None:
                continue
            x, y = d + self._tracker_rng.normal(0.0, self.tracker_noise_mm, 2)
            if self.faults.outlier_rate and self._tracker_rng.random() < self.faults.outlier_rate:
                angle = self._tracker_rng.uniform(0.0, 2 * np.pi)
                off = self._tracker_rng.uniform(5.0, 50.0)
                x, y = x + off * np.cos(angle), y + off * np.sin(angle)
                self.outliers_sent += 1
            if self.tracker_format == "plain":
                line = format_plain(x, y)
            else:
                line = format_pxyt(x, y)
                if self._tracker_rng.random() < self.faults.bad_checksum_rate:
                    cs = int(line[-4:-2], 16) ^ int(self._tracker_rng.integers(1, 256))
                    line = line[:-4] + f"{cs:02X}".encode() + b"\r\n"
            self._write(master, self._corrupt(line, self._tracker_rng, self.faults.drop_rate,
                                              self.faults.garble_rate))


def run_sim_device(rig_dir: str | Path, protocol: str = "maestro", *,
                   effects: Sequence[str] | None = None, seed: int | None = None,
                   out: TextIO = sys.stdout, **kwargs) -> None:
    """``bayesrob sim-device``: serve the rig in ``rig_dir`` (its truth.toml) until stopped.

    Prints ``servo: PATH`` and ``tracker: PATH``, one per line, flushed, then serves until
    SIGTERM or SIGINT.
    """
    import signal

    from bayesrob.data.rig import RigError
    from bayesrob.sim.equilibrium import PhysicalRig
    from bayesrob.sim.truth import TRUTH_FILE, Truth

    truth_path = Path(rig_dir) / TRUTH_FILE
    if not truth_path.is_file():
        raise RigError(f"{truth_path}: file not found (sim-device serves a simulated rig; make "
                       "one with 'bayesrob simulate')")
    truth = Truth.from_toml(truth_path)
    if effects is not None:
        truth = truth.with_effects(effects)
    plant = PhysicalRig(truth, seed)
    device = SimDevice(plant, protocol, seed=truth.seed if seed is None else seed, **kwargs)
    device.start()
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: device.stop())
    try:
        print(f"servo: {device.servo_port}", file=out, flush=True)
        print(f"tracker: {device.tracker_port}", file=out, flush=True)
        device.wait()
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, previous)
        device.stop()
