"""Progress of the long commands: a tqdm bar on a terminal, plain lines everywhere else.

A run whose stderr is redirected (a log file, CI, ``2>&1 | tee``) would see nothing from a
tqdm bar, so off a terminal :class:`Progress` prints a line such as::

    compare: 3/6 models (50%), 12.4 s, cond

at once when it starts (before any compilation, so the run is never silent from its first
second), then at most every ``interval`` seconds, and a last line with "done" when it is
closed. A background thread prints the same line when no step finishes for a whole interval,
so a single slow step (JAX compilation, a NUTS fit) still shows the clock moving; on a
terminal the same thread refreshes the bar's elapsed time.

``progress(total, desc, unit, enabled)`` is the one entry point; ``enabled=False`` prints
nothing at all (library calls default to it; the command line turns it off with
``--no-progress``).
"""

from __future__ import annotations

import os
import sys
import threading
import time
import weakref
from collections.abc import Callable
from typing import IO, Any

INTERVAL_S = 5.0
# A long command's clock starts printing after this long: within the 2 s a person waits for a
# sign of life, yet after the input checks, so bad input gives its one error line alone.
FIRST_LINE_S = 1.0
BAR_REFRESH_S = 1.0


class Progress:
    """A progress report for ``total`` steps of ``unit``; see the module docstring.

    ``tty``: draw a tqdm bar (default: whether ``stream`` is a terminal). ``clock``: seconds,
    for tests. ``heartbeat``: the background thread that reports a step taking longer than
    ``interval`` (off when a test drives a simulated clock).
    """

    def __init__(self, total: int | None, desc: str, unit: str = "step", *,
                 enabled: bool = True, stream: IO[str] | None = None,
                 interval: float = INTERVAL_S, tty: bool | None = None, initial: int = 0,
                 clock: Callable[[], float] = time.monotonic, heartbeat: bool = True,
                 postfix: str = "", first_after: float = 0.0) -> None:
        self._total, self.desc, self.unit = total, desc, unit
        self.n = initial
        self.enabled = enabled
        self.postfix = postfix
        self._stream = stream if stream is not None else sys.stderr
        self._interval = interval
        self._clock = clock
        self._t0 = clock()
        self._last = self._t0
        self._lock = threading.Lock()
        self._closed = not enabled
        self._bar: Any = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if not enabled:
            return
        if tty is None:
            tty = _is_terminal(self._stream)
        if tty:
            from tqdm.auto import tqdm

            self._bar = tqdm(total=total, initial=initial, desc=desc, unit=unit,
                             file=self._stream, leave=False, postfix=postfix or None)
        elif first_after > 0 and heartbeat:
            # the first line when the work has run ``first_after`` seconds: an error in the
            # input, found at once, is then the only line the command prints
            self._last = self._t0 - self._interval + first_after
        else:
            self._emit()
        if heartbeat:
            # The thread holds the report weakly: a report that an exception left unclosed
            # is collected with its frame and stops beating.
            self._thread = threading.Thread(target=_beat, args=(weakref.ref(self),),
                                            name=f"progress-{desc}", daemon=True)
            self._thread.start()

    # -------------------------------------------------------------- what callers use

    def update(self, n: int = 1) -> None:
        """``n`` more steps done."""
        if self._closed:
            return
        with self._lock:
            self.n += n
            if self._bar is not None:
                self._bar.update(n)
            elif self._clock() - self._last >= self._interval:
                self._emit()

    def set_postfix(self, text: str) -> None:
        """What is being worked on now (a model name, an arm), shown after the count."""
        if self._closed:
            return
        with self._lock:
            self.postfix = str(text)
            if self._bar is not None:
                self._bar.set_postfix_str(self.postfix)

    set_postfix_str = set_postfix  # tqdm's name, for callers written against tqdm

    @property
    def total(self) -> int | None:
        return self._total

    @total.setter
    def total(self, total: int | None) -> None:
        """Change the number of steps (when the work turns out longer than planned)."""
        with self._lock:
            self._total = total
            if self._bar is not None and not self._closed:
                self._bar.total = total
                self._bar.refresh()

    def close(self, done: bool = True) -> None:
        """Stop reporting; off a terminal, print the final count with "done" (if ``done``)."""
        if self._closed:
            return
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        with self._lock:
            self._closed = True
            if self._bar is not None:
                self._bar.close()
            elif done:
                self._emit(done=True)

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, *exc: object) -> None:
        # A failed step is not "done": the error message that follows says what happened.
        self.close(done=exc_type is None)

    # -------------------------------------------------------------- lines

    def line(self, done: bool = False) -> str:
        """The status line: "desc: n/total unit (pct), elapsed s[, postfix][, done]"."""
        elapsed = f"{self._clock() - self._t0:.1f} s"
        if self.total:
            parts = [f"{self.desc}: {self.n}/{self.total} {self.unit} "
                     f"({100 * self.n / self.total:.0f}%)", elapsed]
        elif self.n:
            parts = [f"{self.desc}: {self.n} {self.unit}", elapsed]
        else:  # one long step with nothing to count: the clock alone
            parts = [f"{self.desc}: {elapsed}"]
        if self.postfix:
            parts.append(self.postfix)
        if done:
            parts.append("done")
        return ", ".join(parts)

    def _emit(self, done: bool = False) -> None:
        """Print the status line (caller holds the lock or is the constructor)."""
        self._last = self._clock()
        try:
            print(self.line(done), file=self._stream, flush=True)
        except (OSError, ValueError):  # the stream went away (closed pipe, closed file)
            self._closed = True

    def _tick(self) -> bool:
        """One heartbeat; False once the report is closed."""
        with self._lock:
            if self._closed:
                return False
            if self._bar is not None:
                self._bar.refresh()
            elif self._clock() - self._last >= self._interval:
                self._emit()
            return True


def _beat(ref: weakref.ref[Progress]) -> None:
    p = ref()
    if p is None:
        return
    stop, period = p._stop, min(p._interval, BAR_REFRESH_S)
    del p
    while not stop.wait(period):
        p = ref()
        if p is None or not p._tick():
            return
        del p


def _is_terminal(stream: IO[str]) -> bool:
    """A terminal a bar can be drawn on (a pseudo-terminal of width 0 shows no bar)."""
    isatty = getattr(stream, "isatty", None)
    if not (isatty and isatty()):
        return False
    try:
        return os.get_terminal_size(stream.fileno()).columns > 0
    except (AttributeError, OSError, ValueError):
        return True


def progress(total: int | None, desc: str, unit: str = "step", enabled: bool = True,
             **kwargs: Any) -> Progress:
    """A :class:`Progress` (a context manager): a bar on a terminal, lines otherwise."""
    return Progress(total, desc, unit, enabled=enabled, **kwargs)
