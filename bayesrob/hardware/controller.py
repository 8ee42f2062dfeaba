"""What every servo controller shares: the serial link, the safety checks and the settle loop.

A controller moves named arms (each two channels) to pulse widths, waits until it reports them
settled, and reads back what it actually commands. The read-back is the guard against a
command lost or corrupted on the wire: a row is only measured once the controller confirms the
pulses the row will record, and (:meth:`ServoController.dropped_targets`) only recorded if the
controller still outputs them after the measurement.

Settling. A controller whose "still moving?" query can be trusted (the SSC-32's ``Q``) is
polled until it says done, then read back. One whose query can wrongly say "done" (the Micro
Maestro's Get Moving State) is only asked as a hint: a "moving" answer saves the position
queries, a "done" answer is checked by reading back every channel until each equals its target.
A controller that stops short and stays there is sent the move again; stopping at the very same
wrong pulses once more means the controller itself limits the pulse (a channel range), which
re-sending cannot fix, so that is an error naming the channel.

Safety lives here, not in the protocols: every pulse width is checked against the rig's
``pulse_limits`` before the first byte of a move is written, so an out-of-limit request raises
:class:`LimitError` and the port sees nothing.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence

import serial

try:
    import termios
except ImportError:  # Windows
    _PORT_ERRORS: tuple[type[BaseException], ...] = (serial.SerialException, OSError)
else:
    # pyserial lets termios.error through from flush() (tcdrain) on a port that went away.
    _PORT_ERRORS = (serial.SerialException, OSError, termios.error)

Limits = tuple[tuple[float, float], tuple[float, float]]
Channels = dict[str, tuple[int, int]]
Commands = Mapping[str, Sequence[float]]

DEFAULT_TIMEOUT_S = 0.5
DEFAULT_RETRIES = 5
STUCK_STOPS = 3  # identical wrong stops before outputs count as held (see move_and_settle)
DEFAULT_SPEED_US_PER_S = 500.0
# How long read-back positions must stay unchanged, short of the target, to count as stopped.
# A Maestro steps its outputs once per 20 ms servo period, so this spans many steps.
STALL_S = 0.3


class ArgumentError(ValueError):
    """A hardware option is wrong (channels, plan, fault rates); reported as a usage error."""


class HardwareError(RuntimeError):
    """A port cannot be used or a device does not answer as it should; one line for the user."""


class LimitError(HardwareError):
    """A requested pulse width is outside the rig's pulse_limits; nothing was sent."""


class DisconnectedError(HardwareError):
    """The port went away (cable pulled, device reset, power lost)."""


class ShortReplyError(HardwareError):
    """Fewer reply bytes than the command owes arrived before the timeout."""


def open_port(port: str, baud: int, timeout_s: float, what: str) -> serial.Serial:
    """Open a serial port exclusively, so no second program can interleave bytes with ours."""
    if "://" not in port and not port.upper().startswith("COM") and not os.path.exists(port):
        raise HardwareError(f"{what} port {port}: no such device")
    try:
        return serial.Serial(port, baud, timeout=timeout_s, write_timeout=max(timeout_s, 1.0),
                             exclusive=True)
    except (*_PORT_ERRORS, ValueError) as exc:
        raise HardwareError(f"{what} port {port}: cannot open it: {exc}") from None


class SerialLink:
    """A serial port whose failures all surface as :class:`HardwareError` naming the port."""

    def __init__(self, port: serial.Serial, what: str):
        self.port = port
        self.what = what
        self.name = getattr(port, "port", None) or what

    @contextlib.contextmanager
    def _io(self) -> Iterator[None]:
        try:
            yield
        except _PORT_ERRORS as exc:
            raise DisconnectedError(f"lost the {self.what} port {self.name}: {exc}") from None

    def write(self, data: bytes) -> None:
        if not isinstance(data, bytes | bytearray):
            raise TypeError(f"serial data must be bytes, not {type(data).__name__}")
        with self._io():
            n = self.port.write(bytes(data))
            self.port.flush()
        if n is not None and n != len(data):
            raise HardwareError(f"{self.what} port {self.name}: wrote {n} of {len(data)} bytes")

    def read_exact(self, n: int, request: str) -> bytes:
        with self._io():
            data = self.port.read(n)
        if len(data) != n:
            raise ShortReplyError(f"{self.what} port {self.name}: {request} got {len(data)} of "
                                  f"{n} reply bytes within {self.port.timeout} s")
        return data

    def read_until(self, terminator: bytes, request: str, limit: int = 256) -> bytes:
        with self._io():
            data = self.port.read_until(terminator, limit)
        if not data.endswith(terminator):
            raise ShortReplyError(f"{self.what} port {self.name}: {request} got no complete "
                                  f"reply within {self.port.timeout} s (got {data!r})")
        return data

    def readline(self) -> bytes:
        """One line or whatever arrived before the timeout (the caller judges it)."""
        with self._io():
            return self.port.readline()

    def discard_input(self) -> None:
        with self._io():
            self.port.reset_input_buffer()

    @property
    def timeout_s(self) -> float:
        return float(self.port.timeout or 0.0)

    def close(self) -> None:
        # closing a port that vanished is not worth an error on the way out
        with contextlib.suppress(*_PORT_ERRORS):
            self.port.close()


def quantize_us(u: Iterable[float], resolution_us: float) -> tuple[float, ...]:
    """Round pulse widths to a controller's resolution (quarter-us for a Maestro)."""
    return tuple(round(float(v) / resolution_us) * resolution_us for v in u)


def check_limits(commands: Commands, channels: Mapping[str, tuple[int, int]],
                 limits: Mapping[str, Limits]) -> dict[str, tuple[float, float]]:
    """Validate a move before anything is sent; returns the commands as float pairs."""
    out: dict[str, tuple[float, float]] = {}
    for arm, u in commands.items():
        if arm not in channels:
            raise LimitError(f"arm {arm!r} has no channels on this controller "
                             f"(known: {', '.join(channels)})")
        if arm not in limits:
            raise LimitError(f"arm {arm!r} has no pulse_limits")
        pair = tuple(float(v) for v in u)
        if len(pair) != 2:
            raise LimitError(f"arm {arm!r}: expected two pulse widths, got {list(u)!r}")
        for j, (p, (lo, hi)) in enumerate(zip(pair, limits[arm], strict=True)):
            if not math.isfinite(p) or not lo <= p <= hi:
                raise LimitError(f"arm {arm!r} joint {j + 1}: pulse {p:g} us is outside its "
                                 f"pulse_limits [{lo:g}, {hi:g}]; nothing was sent")
        out[arm] = pair  # type: ignore[assignment]
    return out


class ServoController(ABC):
    """A servo controller driving named two-joint arms.

    Subclasses speak one wire protocol; this class owns the safety check, the retries and the
    settle loop, so both protocols behave the same to :func:`bayesrob.hardware.collect.collect`.
    """

    protocol: str = ""
    resolution_us: float = 1.0  # smallest step the controller can command
    readback_tolerance_us: float = 0.0  # how far a read-back may differ from the command
    moving_state_reliable: bool = True  # False: is_moving() may say "done" while still moving

    def __init__(self, link: SerialLink, channels: Mapping[str, tuple[int, int]],
                 limits: Mapping[str, Limits], speed_us_per_s: float | None = None,
                 retries: int = DEFAULT_RETRIES, poll_s: float = 0.005,
                 sleep: Callable[[float], None] = time.sleep):
        self.link = link
        self.channels: Channels = {a: (int(c[0]), int(c[1])) for a, c in channels.items()}
        self.limits = dict(limits)
        self.speed_us_per_s = speed_us_per_s
        self.retries = max(1, int(retries))
        self.poll_s = poll_s
        self._sleep = sleep
        self.resent_moves = 0
        self.failed_queries = 0
        self.stall_s = STALL_S
        self.flagged_errors: list[str] = []  # error flags seen while the targets still held
        self.description = f"{self.protocol} on {link.name}"
        self._targets: dict[int, float] = {}

    # -- protocol hooks ------------------------------------------------------------------
    @abstractmethod
    def connect(self) -> str:
        """Check that the device answers; returns a one-line description of it."""

    @abstractmethod
    def _send_move(self, moves: list[tuple[int, float]]) -> None:
        """Write the bytes that move each (channel, pulse_us) pair."""

    @abstractmethod
    def is_moving(self) -> bool:
        """Whether the controller is still ramping any output towards its target."""

    @abstractmethod
    def channel_position(self, channel: int) -> float:
        """The pulse width (us) the controller currently outputs on a channel."""

    def errors(self) -> list[str]:
        """Error flags the controller reports (and clears); empty if it has no such query."""
        return []

    # -- shared behaviour ----------------------------------------------------------------
    def quantize(self, u: Iterable[float]) -> tuple[float, ...]:
        """Round pulse widths to what the controller can command, so rows record the truth."""
        return quantize_us(u, self.resolution_us)

    def check(self, commands: Commands) -> dict[str, tuple[float, float]]:
        checked = check_limits(commands, self.channels, self.limits)
        for arm, u in checked.items():
            if self.quantize(u) != tuple(u):
                raise LimitError(f"arm {arm!r}: pulses {list(u)} are not multiples of the "
                                 f"{self.protocol} resolution {self.resolution_us:g} us")
        return checked

    def _moves(self, commands: Mapping[str, tuple[float, float]]) -> list[tuple[int, float]]:
        return [(ch, u) for arm, pair in commands.items()
                for ch, u in zip(self.channels[arm], pair, strict=True)]

    def move(self, commands: Commands) -> None:
        """Start a move of one or more arms; raises LimitError with nothing sent if unsafe."""
        checked = self.check(commands)
        moves = self._moves(checked)
        self._send_move(moves)
        self._targets.update(dict(moves))

    def query(self, request: bytes, n_reply: int, what: str,
              valid: Callable[[bytes], bool] | None = None) -> bytes:
        """Send a request and read its fixed-length reply, retrying lost or garbled replies.

        Stale bytes (a late reply to an earlier try) are discarded before each try, and after a
        timeout we wait one more timeout before retrying, so a slow reply cannot be taken for
        the answer to the next request.
        """
        last: HardwareError | None = None
        for attempt in range(self.retries):
            if attempt:
                self.failed_queries += 1
                self._sleep(self.link.timeout_s)
            self.link.discard_input()
            self.link.write(request)
            try:
                reply = self.link.read_exact(n_reply, what)
            except ShortReplyError as exc:
                last = exc
                continue
            if valid is None or valid(reply):
                return reply
            last = HardwareError(f"{self.link.what} port {self.link.name}: {what} got an "
                                 f"invalid reply {reply.hex(' ')}")
        assert last is not None
        raise HardwareError(f"{last} (after {self.retries} tries)")

    def read_positions(self, arms: Iterable[str]) -> dict[str, tuple[float, float]]:
        return {a: (self.channel_position(self.channels[a][0]),
                    self.channel_position(self.channels[a][1])) for a in arms}

    def _matches(self, pos: Mapping[str, tuple[float, float]],
                 commands: Mapping[str, tuple[float, float]]) -> bool:
        return not self._short(pos, commands)

    def settle_timeout_s(self, commands: Mapping[str, tuple[float, float]]) -> float:
        """Time for this move at the configured speed (twice the ramp), plus slack.

        The distance is from the targets last sent; a channel never commanded by us (or whose
        target the controller may have dropped) counts as a full pulse_limits span.
        """
        dist = 0.0
        for arm, pair in commands.items():
            for ch, u, (lo, hi) in zip(self.channels[arm], pair, self.limits[arm], strict=True):
                last = self._targets.get(ch)
                dist = max(dist, hi - lo if last is None else abs(u - last))
        ramp = dist / self.speed_us_per_s if self.speed_us_per_s else 0.0
        return 2.0 * ramp + 2.0 + self.stall_s + 4 * self.retries * self.link.timeout_s

    def _wait(self, checked: Mapping[str, tuple[float, float]], timeout_s: float
              ) -> tuple[bool, dict[str, tuple[float, float]]]:
        """Poll until the read-back equals the commands (True) or the outputs stopped short.

        Returns (arrived, last read-back); raises HardwareError when the deadline passes with
        the outputs still changing.
        """
        deadline = time.monotonic() + timeout_s
        pos: dict[str, tuple[float, float]] = {}
        stopped_elsewhere = 0
        still_since: float | None = None
        while True:
            if not self.is_moving():
                prev, pos = pos, self.read_positions(checked)
                if self._matches(pos, checked):
                    return True, pos
                now = time.monotonic()
                if self.moving_state_reliable:
                    # A read-back taken at the instant the ramp ends may lag; only a mismatch
                    # seen twice while stopped means the target itself is wrong.
                    stopped_elsewhere += 1
                    if stopped_elsewhere >= 2:
                        return False, pos
                elif pos != prev or still_since is None:
                    still_since = now
                elif now - still_since >= self.stall_s:
                    return False, pos
            if time.monotonic() > deadline:
                raise HardwareError(f"{self.protocol}: arms did not settle within "
                                    f"{timeout_s:.1f} s (last read-back {pos or 'none'}, "
                                    f"commanded {dict(checked)})")
            self._sleep(self.poll_s)

    def _short(self, pos: Mapping[str, tuple[float, float]],
               commands: Mapping[str, tuple[float, float]]) -> list[tuple[str, int, int, float,
                                                                           float]]:
        """(arm, joint 1|2, channel, commanded, read back) of every output off its target."""
        tol = self.readback_tolerance_us + 1e-9
        return [(a, j + 1, self.channels[a][j], c, p) for a in commands
                for j, (p, c) in enumerate(zip(pos[a], commands[a], strict=True))
                if abs(p - c) > tol]

    def stuck_error(self, pos: Mapping[str, tuple[float, float]],
                    commands: Mapping[str, tuple[float, float]]) -> HardwareError:
        """The error for outputs that stop at the same wrong pulses after a re-sent move."""
        where = "; ".join(f"channel {ch} (arm {a!r} joint {j}) commanded {c:g} us, stays at "
                          f"{p:g} us" for a, j, ch, c, p in self._short(pos, commands))
        return HardwareError(f"{self.protocol}: {where}; check the controller's channel range "
                             "settings and the wiring")

    def move_and_settle(self, commands: Commands,
                        timeout_s: float | None = None) -> dict[str, tuple[float, float]]:
        """Move, wait until the controller outputs the commanded pulses, return the read-back.

        A controller that stops somewhere else (a command lost or garbled on the wire) gets the
        move again; outputs that leave their earlier targets and stop at the same wrong pulses
        three times are :meth:`stuck_error`, and after ``retries`` moves any mismatch is an error,
        never a recorded row.
        """
        checked = self.check(commands)
        timeout_s = self.settle_timeout_s(checked) if timeout_s is None else timeout_s
        before = dict(self._targets)
        pos: dict[str, tuple[float, float]] = {}
        stops: list[dict[str, tuple[float, float]]] = []
        for _ in range(self.retries):
            self.move(checked)
            arrived, pos = self._wait(checked, timeout_s)
            if arrived:
                return pos
            stops.append(pos)
            # A lost command leaves an output at its earlier target; outputs that left it and
            # stopped short at the very same pulses three times are held there by the
            # controller. Twice is not enough: a move damaged on the wire can leave an output
            # at a wrong target and the re-sent move be lost too (a 20-row collection with 3%
            # of the received bytes damaged was stopped that way in the test suite). An
            # output never commanded before has no known earlier target (it sits wherever the
            # controller started it), so only the tries running out can tell that apart from
            # commands lost on a noisy line. Nor can a range hold an output outside the rig's
            # pulse_limits (a clamp pulls a target inside the limits' span): such an output got
            # a target damaged on the wire, and the resent move puts it right.
            same = len(stops) >= STUCK_STOPS and all(s == pos for s in stops[-STUCK_STOPS:])
            if same and all(
                    before.get(ch) is not None and p != before[ch]
                    and self.limits[a][j - 1][0] <= p <= self.limits[a][j - 1][1]
                    for a, j, ch, _, p in self._short(pos, checked)):
                raise self.stuck_error(pos, checked)
            self.resent_moves += 1
        if len(stops) >= 2 and stops[-1] == stops[-2]:
            raise self.stuck_error(pos, checked)
        raise HardwareError(f"{self.protocol}: controller outputs {pos} instead of the commanded "
                            f"{dict(checked)} after {self.retries} tries; check its channel "
                            "range settings and the wiring")

    def dropped_targets(self, commands: Commands) -> str | None:
        """After a measurement: why the arms may not have held ``commands``, or None if they did.

        Error flags with every output still on target are re-read after a few servo periods:
        a controller sent to a home position with a speed limit leaves the target gradually.
        A mismatch is read twice more before it counts, as a reply damaged or delayed on the
        wire can look like one; a dropped target stays dropped. The targets of dropped outputs are
        forgotten, so the next settle allows a full move.
        """
        checked = {a: (float(u[0]), float(u[1])) for a, u in commands.items()}
        errs = self.errors()
        pos = self.read_positions(checked)
        if errs and self._matches(pos, checked):
            self._sleep(0.05)
            pos = self.read_positions(checked)
        for _ in range(2):
            if self._matches(pos, checked):
                break
            pos = self.read_positions(checked)
        if self._matches(pos, checked):
            self.flagged_errors.extend(errs)
            return None
        for a in checked:
            for ch in self.channels[a]:
                self._targets.pop(ch, None)
        off = ", ".join(f"channel {ch} at {p:g} us instead of {c:g}"
                        for _, _, ch, c, p in self._short(pos, checked))
        flags = f" after reporting {', '.join(errs)}" if errs else ""
        return f"the controller no longer outputs the row's pulses{flags} ({off})"

    def close(self) -> None:
        self.link.close()
