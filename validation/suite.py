"""Running the validation suite: every study (or some), one progress line each, and the
report: ``validation.json`` (what other tools and the docs' tables read) and ``validation.md``.

The report says on which commit, date and machine the figures were measured, and per study
its seeds, figures, targets, each target's outcome, the study's status and seconds. A full run
is what one commits (``validation/validation.json``); the README's and docs' result tables
are generated from that file (:mod:`bayesrob.validation.tables`).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import platform
import subprocess
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

from bayesrob.validation.study import FAIL, KNOWN_MISS, NEWLY_MET, Study

ROOT = Path(__file__).resolve().parent
COMMITTED = ROOT / "validation.json"


def _commit() -> str:
    """The checkout's commit (with '+changes' when the tree differs), or 'unknown'."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True,
                              text=True, timeout=10)
        if head.returncode != 0:
            return "unknown"
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=ROOT, capture_output=True, text=True, timeout=10)
        return head.stdout.strip() + ("+changes" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def machine() -> dict[str, Any]:
    return {"cores": os.cpu_count(), "platform": platform.platform(),
            "python": platform.python_version()}


def _clean(value: Any) -> Any:
    """JSON-safe: numpy scalars to Python numbers, NaN/inf to None."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    if hasattr(value, "item") and not isinstance(value, str):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def run_study(study: Study, quick: bool, say: Callable[[str], None]) -> dict[str, Any]:
    """One study's entry of the report. An exception in the study is its failure (the
    traceback's last line is kept), not the suite's: the other studies still run."""
    seeds = study.seeds(quick)
    t0 = time.monotonic()
    figures: dict[str, Any] = {}
    details: Any = None
    error = ""
    try:
        out = dict(study.runner()(list(seeds), quick=quick, say=say))
        details = out.pop("details", None)
        figures = _clean(out)
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # a broken study is reported, and fails the run
        error = "".join(traceback.format_exception_only(type(exc), exc)).strip()
        say(traceback.format_exc())
    finally:
        from bayesrob import release_compiled_programs

        release_compiled_programs()
    return _entry(study, quick, figures, details, error, time.monotonic() - t0)


def _entry(study: Study, quick: bool, figures: dict[str, Any], details: Any, error: str,
           seconds: float) -> dict[str, Any]:
    checks = study.check(figures, quick) if not error else {t.name: FAIL for t in study.targets}
    status = "fail" if error or FAIL in checks.values() else "pass"
    seeds = study.seeds(quick)
    return {
        "title": study.title,
        "fixed": study.fixed,
        "seeds": {"run": list(seeds), "report": list(study.report_seeds),
                  "tuning": list(study.tuning_seeds)},
        "figures": figures,
        "targets": {t.name: {k: v for k, v in (("min", t.min), ("max", t.max),
                                                ("quick_min", t.quick_min),
                                                ("quick_max", t.quick_max),
                                                ("why", t.why), ("known_miss", t.known_miss))
                             if v not in (None, "")} for t in study.targets},
        "checks": checks,
        "status": status,
        "error": error,
        "seconds": round(seconds, 1),
        "details": _clean(details),
    }


def run_suite(studies: list[Study], quick: bool = False, stream: TextIO | None = None,
              after_each: Callable[[dict[str, Any]], None] | None = None,
              client: Any = None) -> dict[str, Any]:
    """Run ``studies``, a line on ``stream`` (stderr) as each starts and ends; in this process
    in order, or, given a Dask ``client``, each study a task on its cluster (the longest first,
    by the committed report's seconds), side by side. ``after_each(report)`` is called with the
    report so far (``status`` "running") after each study, so an hour's run that is stopped
    keeps what it measured. The report lists the studies in the order given either way."""
    stream = stream if stream is not None else sys.stderr
    report: dict[str, Any] = {
        "commit": _commit(),
        "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "machine": machine(),
        "quick": quick,
        "workers": 1 if client is None else len(client.scheduler_info().get("workers", {})),
        "studies": {},
    }
    order = {s.name: i for i, s in enumerate(studies, 1)}
    done: dict[str, dict[str, Any]] = {}
    t0 = time.monotonic()

    def finished(name: str, entry: dict[str, Any]) -> None:
        done[name] = entry
        report["studies"] = {s.name: done[s.name] for s in studies if s.name in done}
        misses = [n for n, c in entry["checks"].items() if c == FAIL]
        print(f"validate: [{order[name]}/{len(studies)}] {name}: {entry['status']} in "
              f"{_duration(entry['seconds'])}"
              + (f" ({entry['error']})" if entry["error"] else "")
              + (f"; missed: {', '.join(misses)}" if misses and not entry["error"] else ""),
              file=stream, flush=True)
        if after_each is not None:
            after_each({**report, "seconds": round(time.monotonic() - t0, 1),
                        "status": "running"})

    if client is None:
        for study in studies:
            finished(study.name, _start_study(study, quick, order[study.name], len(studies),
                                              stream))
    else:
        from distributed import as_completed

        seconds = _committed_seconds()
        # submitted longest first: a free worker takes a task the moment it is submitted,
        # and the rest wait in the order they came
        longest_first = sorted(studies, key=lambda s: -seconds.get(s.name, 0.0))
        futures = {client.submit(_study_task, study, quick, order[study.name],
                                 len(studies), pure=False): study
                   for study in longest_first}
        for fut in as_completed(futures):
            study = futures[fut]
            try:
                entry = fut.result()
            except Exception as exc:  # the worker died under the study (memory, a crash)
                entry = _entry(study, quick, {}, None, f"{type(exc).__name__}: {exc}", 0.0)
            finished(study.name, entry)
    report["seconds"] = round(time.monotonic() - t0, 1)
    report["status"] = ("fail" if any(s["status"] == "fail" for s in report["studies"].values())
                        else "pass")
    return report


def _start_study(study: Study, quick: bool, i: int, n: int, stream: TextIO) -> dict[str, Any]:
    def say(text: str) -> None:
        print(f"  {text}", file=stream, flush=True)

    print(f"validate: [{i}/{n}] {study.name}: {study.title} "
          f"(seeds {_seed_text(study.seeds(quick))})", file=stream, flush=True)
    return run_study(study, quick, say)


def _study_task(study: Study, quick: bool, i: int, n: int) -> dict[str, Any]:
    """One study as a Dask task: its lines go to the worker's stderr, which the terminal
    shows."""
    return _start_study(study, quick, i, n, sys.stderr)


def _committed_seconds() -> dict[str, float]:
    """Each study's seconds in the committed full run: the order that finishes soonest on a
    cluster starts the longest first."""
    try:
        studies = json.loads(COMMITTED.read_text())["studies"]
        return {name: float(s.get("seconds") or 0.0) for name, s in studies.items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


def _seed_text(seeds: tuple[int, ...] | list[int]) -> str:
    seeds = list(seeds)
    if len(seeds) > 2 and seeds == list(range(seeds[0], seeds[0] + len(seeds))):
        return f"{seeds[0]}-{seeds[-1]}"
    return ", ".join(map(str, seeds)) or "none"


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.1f} min"


def _figure_text(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return "missing" if value is None else str(value)


def markdown(report: dict[str, Any]) -> str:
    """``validation.md``: the run, then a table per study of figure, value, target, outcome."""
    kind = "quick run (one or two seeds a study; targets not judged)" if report["quick"] \
        else "full run"
    lines = [
        "# Validation",
        "",
        f"{kind.capitalize()} on commit `{report['commit']}`, {report['date']}, "
        f"{report['machine']['cores']} cores ({report['machine']['platform']}): "
        f"**{report['status']}** in {_duration(report['seconds'])}"
        + (f", {report['workers']} studies at a time" if report.get("workers", 1) > 1 else "")
        + ".",
        "",
        *([report["note"] + ".", ""] if report.get("note") else []),
        "| study | seeds | status | time |",
        "| --- | --- | --- | --- |",
    ]
    for name, s in report["studies"].items():
        lines.append(f"| [{name}](#{name.replace('_', '-')}) | {_seed_text(s['seeds']['run'])} "
                     f"| {s['status']} | {_duration(s['seconds'])} |")
    for name, s in report["studies"].items():
        lines += ["", f"## {name}", "", f"{s['title']}. Seeds run: {_seed_text(s['seeds']['run'])}"
                  f" (report {_seed_text(s['seeds']['report'])}; tuning, never reported: "
                  f"{_seed_text(s['seeds']['tuning'])}). Targets: {s['fixed']}."]
        if s["error"]:
            lines += ["", f"**Error:** `{s['error']}`"]
        lines += ["", "| figure | value | target | outcome |", "| --- | --- | --- | --- |"]
        targets = s["targets"]
        for fig in sorted(set(s["figures"]) | set(targets)):
            t = targets.get(fig, {})
            low, high = t.get("min"), t.get("max")
            rng = ("recorded" if low is None and high is None else
                   f"{low:g} to {high:g}" if low is not None and high is not None else
                   f">= {low:g}" if low is not None else f"<= {high:g}")
            outcome = s["checks"].get(fig, "recorded")
            if outcome in (KNOWN_MISS, NEWLY_MET):
                outcome += f" ({t.get('known_miss', '')})"
            lines.append(f"| `{fig}` | {_figure_text(s['figures'].get(fig))} | {rng} | "
                         f"{outcome} |")
    return "\n".join(lines) + "\n"


def write_report(report: dict[str, Any], out: Path) -> tuple[Path, Path]:
    """Write ``validation.json`` and ``validation.md`` into ``out``, each replaced whole."""
    out.mkdir(parents=True, exist_ok=True)
    paths = out / "validation.json", out / "validation.md"
    texts = json.dumps(report, indent=2) + "\n", markdown(report)
    for path, text in zip(paths, texts, strict=True):
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    return paths


def load_committed(path: Path = COMMITTED) -> dict[str, Any]:
    return json.loads(path.read_text(encoding="utf-8"))
