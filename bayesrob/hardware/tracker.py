"""Where the end point is: a streaming position tracker on a serial port, or a person typing.

The streaming tracker sends lines continuously. Two formats:

- ``pxyt`` (default): ``$PXYT,<x_mm>,<y_mm>*HH\\r\\n``, HH the hexadecimal XOR of every
  character between ``$`` and ``*`` (the NMEA 0183 checksum), so a corrupted line is caught.
- ``plain``: ``<x_mm>,<y_mm>\\r\\n``, for trackers without a checksum (a corrupted digit there
  goes unnoticed; rejecting readings far from the median of several is the only defence).

A reading is taken after the arm has settled: the input buffer (readings from while the arm
moved) is discarded, the first, probably partial, line is dropped, and ``samples`` good lines
are read. The XOR checksum cannot see two equal bytes lost from one line (``256.044`` arriving
as ``256.0`` keeps its checksum), so a line must also print its numbers as the stream does:
the same count of decimals in each field as most lines so far (:func:`number_layout`; not
enforced while a stream's own lines disagree, as a tracker printing ``%g`` would).
Readings far from their median (:func:`reject_outliers`: a robust scale from the
median distance, with a floor) are rejected and counted; the mean of the rest is the
measurement.

Manual entry is for measuring as the paper did, with a ruler-like device: the operator types
``x y`` for each point, and anything else is asked again, never recorded.
"""

from __future__ import annotations

import functools
import math
import operator
import sys
import time
from collections import Counter
from collections.abc import Callable
from typing import Literal, Protocol

import numpy as np

from bayesrob.hardware.controller import HardwareError, SerialLink

TrackerFormat = Literal["pxyt", "plain"]
FORMATS: tuple[str, ...] = ("pxyt", "plain")
SENTENCE = "PXYT"


class TrackerLineError(ValueError):
    """A tracker line that cannot be used; ``kind`` is 'checksum' or 'malformed'."""

    def __init__(self, kind: str, message: str):
        super().__init__(message)
        self.kind = kind


class Tracker(Protocol):
    def measure(self, label: str) -> np.ndarray:
        """The end point (x, y) in mm of the current pose; ``label`` says which row it is."""
        ...


def checksum(body: str | bytes) -> int:
    """XOR of the characters between '$' and '*'."""
    data = body.encode("ascii") if isinstance(body, str) else body
    return functools.reduce(operator.xor, data, 0)


def format_pxyt(x_mm: float, y_mm: float, decimals: int = 3) -> bytes:
    body = f"{SENTENCE},{x_mm:.{decimals}f},{y_mm:.{decimals}f}"
    return f"${body}*{checksum(body):02X}\r\n".encode("ascii")


def format_plain(x_mm: float, y_mm: float, decimals: int = 3) -> bytes:
    return f"{x_mm:.{decimals}f},{y_mm:.{decimals}f}\r\n".encode("ascii")


def number_layout(line: bytes) -> tuple[int, ...]:
    """Decimals of each number in a tracker line (-1: no decimal point): what a device that
    prints a fixed format keeps the same from line to line."""
    text = line.decode("ascii", "replace").strip("\r\n").lstrip("$").partition("*")[0]
    fields = text.split(",")
    if fields and fields[0] == SENTENCE:
        fields = fields[1:]
    return tuple(len(f.partition(".")[2]) if "." in f else -1 for f in fields)


# A stream counts as printing a fixed format once this many lines were seen and at least this
# share of them had the most common layout; then lines of another layout are refused.
LAYOUT_MIN_LINES = 5
LAYOUT_SHARE = 0.75


def _xy(fields: list[str], line: bytes) -> tuple[float, float]:
    if len(fields) != 2:
        raise TrackerLineError("malformed", f"expected two numbers in {line!r}")
    try:
        x, y = float(fields[0]), float(fields[1])
    except ValueError:
        raise TrackerLineError("malformed", f"not numbers in {line!r}") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise TrackerLineError("malformed", f"not finite numbers in {line!r}")
    return x, y


def parse_line(line: bytes, fmt: TrackerFormat = "pxyt") -> tuple[float, float]:
    """One complete tracker line (with or without its line ending) to (x_mm, y_mm)."""
    try:
        text = line.decode("ascii").strip("\r\n")
    except UnicodeDecodeError:
        raise TrackerLineError("malformed", f"non-ASCII bytes in {line!r}") from None
    if fmt == "plain":
        return _xy(text.split(","), line)
    if fmt != "pxyt":
        raise ValueError(f"unknown tracker format {fmt!r} (choose from {', '.join(FORMATS)})")
    if not text.startswith("$") or text.count("*") != 1:
        raise TrackerLineError("malformed", f"not a $PXYT sentence: {line!r}")
    body, _, hh = text[1:].partition("*")
    if len(hh) != 2 or any(c not in "0123456789abcdefABCDEF" for c in hh):
        raise TrackerLineError("malformed", f"bad checksum field in {line!r}")
    if int(hh, 16) != checksum(body):
        raise TrackerLineError("checksum", f"checksum {hh} does not match "
                                           f"{checksum(body):02X} in {line!r}")
    fields = body.split(",")
    if fields[0] != SENTENCE:
        raise TrackerLineError("malformed", f"not a {SENTENCE} sentence: {line!r}")
    return _xy(fields[1:], line)


# Rejection threshold in robust standard deviations: a 2-D Gaussian reading lies beyond 3.5 sd
# of its centre with probability exp(-3.5**2 / 2) = 0.2 %, so few good readings are lost.
OUTLIER_SD = 3.5
# Floor of the robust sd (mm), so that readings agreeing to the last digit (a median distance
# of zero) do not make every reading a hair away an outlier.
OUTLIER_FLOOR_MM = 0.05
# Median distance of a 2-D Gaussian reading from its centre, in sd: sqrt(2 ln 2) (Rayleigh).
_RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))


def reject_outliers(readings: np.ndarray, n_sd: float = OUTLIER_SD,
                    floor_mm: float = OUTLIER_FLOOR_MM) -> tuple[np.ndarray, int]:
    """The readings (n, 2) within ``n_sd`` robust sd of their median, and how many were not.

    The sd is estimated from the median distance to the coordinate-wise median (a Rayleigh
    median for 2-D Gaussian noise), never below ``floor_mm``. At least half the readings are
    always kept: those no farther than the median distance.
    """
    r = np.asarray(readings, float)
    if r.ndim != 2 or r.shape[1] != 2 or len(r) == 0:
        raise ValueError(f"expected readings of shape (n, 2), got {r.shape}")
    dist = np.linalg.norm(r - np.median(r, axis=0), axis=1)
    sd = max(float(np.median(dist)) / _RAYLEIGH_MEDIAN, floor_mm)
    keep = dist <= n_sd * sd
    return r[keep], int((~keep).sum())


class StreamTracker:
    """A tracker that streams readings continuously over a serial port."""

    def __init__(self, link: SerialLink, fmt: TrackerFormat = "pxyt", samples: int = 5,
                 timeout_s: float = 3.0, outlier_floor_mm: float = OUTLIER_FLOOR_MM):
        if fmt not in FORMATS:
            raise ValueError(f"unknown tracker format {fmt!r} (choose from {', '.join(FORMATS)})")
        if samples < 1:
            raise ValueError(f"samples must be at least 1, got {samples}")
        self.link = link
        self.fmt: TrackerFormat = fmt
        self.samples = samples
        self.timeout_s = timeout_s
        self.bad_checksum = 0
        self.malformed = 0
        self.readings = 0
        self.outliers = 0  # good lines rejected as far from their median
        self.outlier_floor_mm = outlier_floor_mm
        self.layouts: Counter[tuple[int, ...]] = Counter()  # of every line that parsed

    def _fixed_layout(self) -> tuple[int, ...] | None:
        """The stream's number layout, once its lines agree on one (else None)."""
        total = sum(self.layouts.values())
        if total < LAYOUT_MIN_LINES:
            return None
        layout, n = self.layouts.most_common(1)[0]
        return layout if n >= LAYOUT_SHARE * total else None

    def read_samples(self) -> np.ndarray:
        """``samples`` good readings (samples, 2) taken from now on."""
        self.link.discard_input()
        # Whatever arrives first may be the tail of a line the tracker was half-way through.
        self.link.readline()
        parsed: list[tuple[tuple[float, float], tuple[int, ...]]] = []

        def good() -> list[tuple[float, float]]:
            fixed = self._fixed_layout()
            return [xy for xy, lay in parsed if fixed is None or lay == fixed]

        deadline = time.monotonic() + self.timeout_s
        while len(good()) < self.samples:
            if time.monotonic() > deadline:
                raise HardwareError(
                    f"tracker port {self.link.name}: {len(good())} of {self.samples} good "
                    f"readings within {self.timeout_s:g} s ({self.bad_checksum} bad checksums, "
                    f"{self.malformed} malformed lines so far); check the port, baud and "
                    f"--tracker-format")
            line = self.link.readline()
            if not line.endswith(b"\n"):
                continue  # timed out mid-line: the deadline decides
            try:
                xy = parse_line(line, self.fmt)
            except TrackerLineError as exc:
                if exc.kind == "checksum":
                    self.bad_checksum += 1
                else:
                    self.malformed += 1
                continue
            layout = number_layout(line)
            self.layouts[layout] += 1
            parsed.append((xy, layout))
        kept = good()
        # lines of another layout than the stream's passed their checksum but lost bytes
        self.malformed += len(parsed) - len(kept)
        self.readings += self.samples
        return np.asarray(kept[:self.samples])

    def measure(self, label: str = "") -> np.ndarray:
        # A checksum cannot catch a wild reading (a reflection, a marker seen twice); rejecting
        # those first lets the mean use every good reading instead of the median's one or two.
        kept, rejected = reject_outliers(self.read_samples(), floor_mm=self.outlier_floor_mm)
        self.outliers += rejected
        return kept.mean(axis=0)


def parse_manual(text: str) -> tuple[float, float]:
    """``x y`` (or ``x,y``) in mm, as an operator types it; raises ValueError otherwise."""
    parts = text.replace(",", " ").split()
    if len(parts) != 2:
        raise ValueError("type two numbers, x and y in mm, e.g. '123.5 208'")
    try:
        x, y = float(parts[0]), float(parts[1])
    except ValueError:
        raise ValueError(f"not numbers: {text.strip()!r}") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ValueError(f"not finite numbers: {text.strip()!r}")
    return x, y


class ManualTracker:
    """The operator measures and types each end point."""

    def __init__(self, read: Callable[[str], str] = input,
                 write: Callable[[str], None] | None = None, max_attempts: int | None = None):
        self.read = read
        self.write = write or (lambda s: print(s, file=sys.stderr, flush=True))
        self.max_attempts = max_attempts
        self.rejected = 0

    def measure(self, label: str = "") -> np.ndarray:
        attempts = 0
        while True:
            try:
                text = self.read(f"{label} end point x y (mm)> " if label else "x y (mm)> ")
            except EOFError:
                raise HardwareError("manual entry: input ended before the point was "
                                    "measured") from None
            try:
                return np.asarray(parse_manual(text), float)
            except ValueError as exc:
                self.rejected += 1
                attempts += 1
                self.write(f"  not recorded: {exc}")
                if self.max_attempts is not None and attempts >= self.max_attempts:
                    raise HardwareError(f"manual entry: {attempts} invalid answers in a "
                                        "row") from None
