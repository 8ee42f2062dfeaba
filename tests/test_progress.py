"""The progress helper: lines off a terminal (at once, then every interval), a bar on one,
nothing when disabled."""

from __future__ import annotations

import io
import re
import time

from bayesrob.progress import progress


class Clock:
    """A simulated clock the test moves by hand."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class NotATerminal(io.StringIO):
    def isatty(self) -> bool:
        return False


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def _lines(stream: io.StringIO) -> list[str]:
    return stream.getvalue().splitlines()


def test_lines_off_a_terminal_at_once_then_every_interval_then_done():
    out, clock = NotATerminal(), Clock()
    p = progress(6, "compare", "models", stream=out, clock=clock, heartbeat=False)
    # The start line is printed before any step: a redirected run is never silent.
    assert _lines(out) == ["compare: 0/6 models (0%), 0.0 s"]
    clock.t += 2.0
    p.set_postfix("cond")
    p.update()
    assert len(_lines(out)) == 1  # 2 s < 5 s: no new line yet
    clock.t += 3.5
    p.update(2)
    assert _lines(out)[-1] == "compare: 3/6 models (50%), 5.5 s, cond"
    clock.t += 1.0
    p.update()
    assert len(_lines(out)) == 2  # 1 s after the last line
    clock.t += 10.0
    p.close()
    assert _lines(out)[-1] == "compare: 4/6 models (67%), 16.5 s, cond, done"
    p.update()  # after close: ignored
    p.close()
    assert len(_lines(out)) == 3


def test_context_manager_closes_with_done_line():
    out, clock = NotATerminal(), Clock()
    with progress(2, "simulate", "pt", stream=out, clock=clock, heartbeat=False) as p:
        p.update(2)
    assert _lines(out) == ["simulate: 0/2 pt (0%), 0.0 s", "simulate: 2/2 pt (100%), 0.0 s, done"]


def test_no_total_shows_the_clock_and_the_count():
    out, clock = NotATerminal(), Clock()
    p = progress(None, "calibrate", stream=out, clock=clock, heartbeat=False)
    p.set_postfix("NUTS posterior of each arm")
    clock.t += 7.25
    p.update()
    p.close()
    assert _lines(out) == ["calibrate: 0.0 s",
                           "calibrate: 1 step, 7.2 s, NUTS posterior of each arm",
                           "calibrate: 1 step, 7.2 s, NUTS posterior of each arm, done"]


def test_growing_total_is_reported():
    out, clock = NotATerminal(), Clock()
    p = progress(2, "diagnose", "fits", stream=out, clock=clock, heartbeat=False)
    p.update(2)
    p.total = p.n + 1
    p.close()
    assert _lines(out)[-1] == "diagnose: 2/3 fits (67%), 0.0 s, done"


def test_heartbeat_reports_a_long_step_without_updates():
    """One slow step (compilation): the clock still shows, roughly every interval."""
    out = NotATerminal()
    p = progress(3, "sample", "chunks", stream=out, interval=0.05)
    time.sleep(0.4)
    n_during = len(_lines(out))
    p.close()
    lines = _lines(out)
    # Start line, then one line per 0.05 s interval (heartbeat polls every 0.05 s): 0.4 s
    # gives up to 8; a loaded machine may run the thread late, so ask for at least two.
    assert n_during >= 3, lines
    assert all(re.fullmatch(r"sample: 0/3 chunks \(0%\), \d+\.\d s", x) for x in lines[:-1])
    assert lines[-1].endswith(", done")
    time.sleep(0.15)
    assert len(_lines(out)) == len(lines)  # the thread stopped with close()


def test_disabled_prints_nothing():
    out, clock = NotATerminal(), Clock()
    p = progress(4, "reproduce", stream=out, clock=clock, enabled=False)
    clock.t += 60
    p.set_postfix("ind")
    p.update(4)
    p.total = 5
    p.close()
    assert out.getvalue() == ""
    assert p.n == 0  # a disabled report counts nothing either


def test_terminal_gets_a_tqdm_bar_not_lines():
    out = Terminal()
    with progress(4, "nuts", "chunks", stream=out, heartbeat=False) as p:
        p.update(4)
    text = out.getvalue()
    assert "nuts:" in text and "0/4" in text and "\r" in text  # tqdm draws in place
    assert "done" not in text  # the line format is for logs only


def test_closed_stream_does_not_raise():
    out = NotATerminal()
    p = progress(3, "collect", "rows", stream=out, heartbeat=False, interval=0.0)
    out.close()
    p.update()  # printing to a closed stream: the report stops, the work goes on
    p.close()


def test_an_unclosed_report_stops_when_it_is_dropped():
    """A report an exception left open must not print into the rest of the run."""
    import gc

    out = NotATerminal()
    p = progress(3, "reproduce", stream=out, interval=0.05)
    time.sleep(0.12)
    del p
    gc.collect()
    time.sleep(0.1)  # a beat already past its check may print once more
    n = len(_lines(out))
    time.sleep(0.3)
    assert n >= 2 and len(_lines(out)) == n


def test_a_failed_step_is_not_reported_done():
    out, clock = NotATerminal(), Clock()
    try:
        with progress(None, "calibrate", stream=out, clock=clock, heartbeat=False):
            raise RuntimeError("rig error")
    except RuntimeError:
        pass
    assert _lines(out) == ["calibrate: 0.0 s"]
