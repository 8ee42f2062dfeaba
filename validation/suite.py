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
    checks = study.check(figures, quick) if not error else {t.name: FAIL for t in study.targets}
    status = "fail" if error or FAIL in checks.values() else "pass"
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
        "seconds": round(time.monotonic() - t0, 1),
        "details": _clean(details),
    }


def run_suite(studies: list[Study], quick: bool = False, stream: TextIO | None = None,
              after_each: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
    """Run ``studies`` in order, a line on ``stream`` (stderr) as each starts and ends.
    ``after_each(report)`` is called with the report so far (``status`` "running") after
    each study, so an hour's run that is stopped keeps what it measured."""
    stream = stream if stream is not None else sys.stderr

    def say(text: str) -> None:
        print(f"  {text}", file=stream, flush=True)

    report: dict[str, Any] = {
        "commit": _commit(),
        "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "machine": machine(),
        "quick": quick,
        "studies": {},
    }
    t0 = time.monotonic()
    for i, study in enumerate(studies, 1):
        print(f"validate: [{i}/{len(studies)}] {study.name}: {study.title} "
              f"(seeds {_seed_text(study.seeds(quick))})", file=stream, flush=True)
        entry = run_study(study, quick, say)
        report["studies"][study.name] = entry
        misses = [n for n, c in entry["checks"].items() if c == FAIL]
        print(f"validate: [{i}/{len(studies)}] {study.name}: {entry['status']} in "
              f"{_duration(entry['seconds'])}"
              + (f" ({entry['error']})" if entry["error"] else "")
              + (f"; missed: {', '.join(misses)}" if misses and not entry["error"] else ""),
              file=stream, flush=True)
        if after_each is not None:
            after_each({**report, "seconds": round(time.monotonic() - t0, 1),
                        "status": "running"})
    report["seconds"] = round(time.monotonic() - t0, 1)
    report["status"] = ("fail" if any(s["status"] == "fail" for s in report["studies"].values())
                        else "pass")
    return report


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
        f"**{report['status']}** in {_duration(report['seconds'])}.",
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
