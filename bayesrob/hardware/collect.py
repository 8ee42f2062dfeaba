"""``bayesrob collect``: the paper's data-collection procedure on a real (or simulated) rig.

For each arm: commands aimed at an N x N grid over the workspace through the arm's nominal
model (``train``), then the very same commands again (``validation``). Then, once the operator
has linked the arms' end points, every arm aims at each grid point through its own inverse
model (calibrated on the train rows already recorded, if there are enough; else nominal): the
linked ``test`` rows. With ``holdout`` in the plan, rows at new poses too (the grid shifted by
half a cell, ``bayesrob.sim.holdout_points``): each arm's after its validation rows, and
linked ones after the test rows, aimed like them. The default plan is the paper's.

Every row goes to ``measurements.csv`` as soon as it is measured, in one ``write`` of the whole
line followed by ``fsync``, so a run cut short by Ctrl-C, a kill or a lost port leaves a valid
file holding every completed row. ``resume`` re-plans the same run and skips the rows already
recorded, matching them by config, set, commands and target in plan order.
"""

from __future__ import annotations

import contextlib
import csv
import functools
import io
import os
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from bayesrob.data.rig import (
    MEASUREMENTS_FILE,
    N_ARM_PARAMS,
    RIG_FILE,
    SETS,
    ArmSpec,
    RigError,
    csv_records,
    format_row,
    load_rig_toml,
    measurement_header,
    parse_number,
    row_set,
)
from bayesrob.hardware.controller import (
    DEFAULT_RETRIES,
    DEFAULT_SPEED_US_PER_S,
    DEFAULT_TIMEOUT_S,
    ArgumentError,
    HardwareError,
    LimitError,
    SerialLink,
    ServoController,
    check_limits,
    open_port,
    quantize_us,
)
from bayesrob.hardware.tracker import ManualTracker, StreamTracker, Tracker, TrackerFormat

if TYPE_CHECKING:
    from bayesrob.robot import Arm

PROTOCOLS = ("maestro", "ssc32")
# Measurements of one row before giving up on a controller that keeps dropping its targets.
ROW_TRIES = 3
Workspace = tuple[tuple[float, float], tuple[float, float]]  # ((x0, x1), (y0, y1)) in mm
Quantize = Callable[[Iterable[float]], tuple[float, ...]]
TARGET_DECIMALS = 2  # targets are rounded so the recorded text is exactly the point aimed at
# The paper's procedure. Holdout rows are asked for by name: a run begun without them resumes
# to the same plan.
DEFAULT_PLAN = ("train", "validation", "test")
LINKED_SETS = ("test", "holdout")
_MATCH_TOL = 1e-6


# ------------------------------------------------------------------------------ arguments


def parse_channels(tokens: Sequence[str]) -> dict[str, tuple[int, int]]:
    """``["top=0,1", "bottom=2,3"]`` -> ``{"top": (0, 1), "bottom": (2, 3)}``."""
    out: dict[str, tuple[int, int]] = {}
    for tok in tokens:
        name, eq, chans = tok.partition("=")
        name = name.strip()
        if not eq or not name:
            raise ArgumentError(f"--channels: expected ARM=CH1,CH2, got {tok!r}")
        parts = [p.strip() for p in chans.split(",")]
        if len(parts) != 2 or not all(p.isdigit() for p in parts):
            raise ArgumentError(f"--channels: arm {name!r} needs two channel numbers "
                             f"(shoulder,elbow), got {chans!r}")
        if name in out:
            raise ArgumentError(f"--channels: arm {name!r} given twice")
        out[name] = (int(parts[0]), int(parts[1]))
    return out


def check_channels(channels: dict[str, tuple[int, int]], arm_names: Iterable[str],
                   n_channels: int, controller: str = "this controller") -> None:
    """Every rig arm has two distinct channels the controller has; nothing else is named."""
    arm_names = list(arm_names)
    for name in channels:
        if name not in arm_names:
            raise ArgumentError(f"--channels: unknown arm {name!r} (rig.toml has "
                             f"{', '.join(arm_names)})")
    for name in arm_names:
        if name not in channels:
            raise ArgumentError(f"--channels: no channels given for arm {name!r}")
    seen: dict[int, str] = {}
    for name, chs in channels.items():
        for ch in chs:
            if not 0 <= ch < n_channels:
                raise ArgumentError(f"--channels: channel {ch} of arm {name!r} does not exist "
                                 f"({controller} has channels 0..{n_channels - 1})")
            if ch in seen:
                raise ArgumentError(f"--channels: channel {ch} is given to both {seen[ch]!r} "
                                 f"and {name!r}")
            seen[ch] = name


def parse_plan(text: str) -> tuple[str, ...]:
    """``train,validation,test,holdout`` (any non-empty subset); always run in that order."""
    items = [s.strip() for s in text.split(",") if s.strip()]
    for s in items:
        if s not in SETS:
            raise ArgumentError(f"--plan: unknown set {s!r} (choose from {', '.join(SETS)})")
    if not items:
        raise ArgumentError("--plan: name at least one set")
    return tuple(s for s in SETS if s in items)


# ------------------------------------------------------------------------------ the plan


@dataclass(frozen=True)
class Step:
    """One row to measure: which arms, which set, the commands and (linked rows) the target."""

    config: str
    set: str
    commands: dict[str, tuple[float, float]]
    target: tuple[float, float] | None = None

    def matches(self, row: RecordedRow) -> bool:
        if (row.config, row.set, row.target is None) != (self.config, self.set,
                                                         self.target is None):
            return False
        if self.target is not None and not _close(row.target or (), self.target):
            return False
        return set(row.commands) == set(self.commands) and all(
            _close(row.commands[a], self.commands[a]) for a in self.commands)

    def describe(self) -> str:
        cmds = " ".join(f"{a}=[{u[0]:g}, {u[1]:g}]" for a, u in self.commands.items())
        aim = f" aiming at ({self.target[0]:g}, {self.target[1]:g})" if self.target else ""
        return f"{self.config} {self.set}{aim}: {cmds}"


def _close(a: Sequence[float], b: Sequence[float]) -> bool:
    return all(abs(x - y) <= _MATCH_TOL * max(1.0, abs(y)) for x, y in zip(a, b, strict=True))


def grid_targets(workspace: Workspace, n: int, set: str = "train") -> np.ndarray:
    """The N x N grid of ``bayesrob.sim.grid_points`` (for ``holdout``, its cell centres,
    ``holdout_points``), rounded to TARGET_DECIMALS."""
    from bayesrob.sim.rigs import grid_points, holdout_points

    points = holdout_points if set == "holdout" else grid_points
    return np.round(points(workspace, n), TARGET_DECIMALS)


def _aim(arm: Arm, points: np.ndarray, quantize: Quantize, what: str
         ) -> list[tuple[float, float]]:
    import jax.numpy as jnp

    reach = np.asarray(arm.reachable(jnp.asarray(points)))
    if not reach.all():
        p = points[~reach][0]
        raise RigError(f"grid point ({p[0]:g}, {p[1]:g}) is out of reach of arm "
                       f"{arm.name!r}'s {what} model; shrink the workspace in {RIG_FILE}")
    u = np.asarray(arm.command(jnp.asarray(points)))
    return [quantize(row) for row in u]  # type: ignore[misc]


def single_arm_steps(specs: dict[str, ArmSpec], workspace: Workspace, grid: int,
                     quantize: Quantize, sets: Sequence[str] = SETS) -> list[Step]:
    """Train, validation then holdout rows of each arm, in rig order, aimed through the
    nominal model (holdout rows at the grid's cell centres)."""
    from bayesrob.robot import Arm

    steps = []
    for name, spec in specs.items():
        for s in ("train", "validation", "holdout"):
            if s in sets:
                cmds = _aim(Arm.nominal(spec), grid_targets(workspace, grid, s), quantize,
                            "nominal")
                steps += [Step(name, s, {name: u}) for u in cmds]
    return steps


def read_plan(path: str | Path, arms: dict[str, int]
              ) -> tuple[list[str], list[str], dict[str, np.ndarray]]:
    """A ``poses.csv`` of ``bayesrob plan``: each row's config (the arm measured; may be left
    out when there is one arm), set, and every arm's ``<arm>_u1..`` (``arms``: arm -> columns;
    NaN where a row leaves an arm out). A mistake is a RigError naming line and column."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise RigError(f"{path}: cannot read the poses file: {exc.strerror}") from None
    rows = list(csv.reader(io.StringIO(text, newline="")))
    header = [h.strip() for h in rows[0]] if rows else []
    idx = {h: i for i, h in enumerate(header)}
    if "config" not in idx and len(arms) > 1:
        raise RigError(f"{path}: missing column 'config'")
    configs, sets = [], []
    cmds: dict[str, list[list[float]]] = {a: [] for a in arms}
    for _, _, where, row in csv_records(path, header, rows[1:], range(2, len(rows) + 1)):
        arm = row[idx["config"]].strip() if "config" in idx else next(iter(arms))
        if arm not in arms:
            raise RigError(f"{where}: config {arm!r} is not an arm of the rig "
                           f"({', '.join(arms)})")
        st = row_set(row, idx, where) if "set" in idx else "train"
        for a, m in arms.items():
            cols = [f"{a}_u{k + 1}" for k in range(m)]
            missing = [c for c in cols if c not in idx]
            if missing and a == arm:
                raise RigError(f"{path}: missing column {missing[0]!r}")
            cmds[a].append([parse_number(row[idx[c]], where, c, allow_empty=a != arm)
                            if c in idx else float("nan") for c in cols])
        configs.append(arm)
        sets.append(st)
    if not configs:
        raise RigError(f"{path}: no poses in the file")
    return configs, sets, {a: np.array(v, float) for a, v in cmds.items()}


def plan_steps(path: str | Path, specs: dict[str, ArmSpec], quantize: Quantize) -> list[Step]:
    """The rows of a ``poses.csv`` as steps, in its order (each measures its config's arm)."""
    configs, sets, cmds = read_plan(path, {n: 2 for n in specs})
    return [Step(c, s, {c: quantize(cmds[c][i])})
            for i, (c, s) in enumerate(zip(configs, sets, strict=True))]


def append_planned(rig_dir: str | Path, path: str | Path) -> int:
    """Append a ``poses.csv``'s rows to a planar rig's measurements.csv as planned rows (x, y
    empty), for ``simulate --poses`` to measure. Returns how many."""
    rig_dir = Path(rig_dir)
    names = list(load_rig_toml(rig_dir / RIG_FILE)["arms"])
    configs, sets, cmds = read_plan(path, {n: 2 for n in names})
    lines = [_csv_line(format_row(names, c, s, None, {c: cmds[c][i]},
                                  (float("nan"), float("nan"))))
             for i, (c, s) in enumerate(zip(configs, sets, strict=True))]
    target = rig_dir / MEASUREMENTS_FILE
    with target.open("a", encoding="utf-8", newline="") as fh:
        fh.write("".join(lines))
    return len(lines)


def measure_plan_in_simulation(rig_dir: str | Path, path: str | Path, seed: int = 0,
                               progress: bool = False) -> int:
    """``simulate --poses FILE``: measure a ``poses.csv``'s rows, in its order, on the
    simulated rig in ``rig_dir`` (its truth.toml), appending them. Returns how many."""
    import tomllib

    from bayesrob.sim.rigs import measure_arm6_poses, measure_planned
    from bayesrob.sim.truth import TRUTH_FILE

    truth = Path(rig_dir) / TRUTH_FILE
    if not truth.is_file():
        raise RigError(f"{truth}: file not found (--poses FILE measures on a rig made by "
                       "'bayesrob simulate'; use 'bayesrob collect --plan' on hardware)")
    # the truth file's table says which simulator made the rig ("chain_truth" is also a
    # substring of "linked_chain_truth": match the tables, not the text)
    tables = tomllib.loads(truth.read_text())
    if "linked_chain_truth" in tables:
        # each planned row measures its config's arm alone, as bayesrob plan chose it
        configs, sets, cmds = read_plan(path, {a: 6 for a in tables["linked_chain_truth"]["arms"]})
        q = np.array([cmds[c][i] for i, c in enumerate(configs)])
        return measure_arm6_poses(rig_dir, sets, q, seed=seed, configs=configs)
    if "chain_truth" in tables:
        _, sets, cmds = read_plan(path, {"arm": 6})
        return measure_arm6_poses(rig_dir, sets, cmds["arm"], seed=seed)
    append_planned(rig_dir, path)
    return measure_planned(rig_dir, seed=seed, progress=progress)[0]


def linked_steps(specs: dict[str, ArmSpec], arms: dict[str, Arm], workspace: Workspace,
                 grid: int, quantize: Quantize, sets: Sequence[str] = ("test",)) -> list[Step]:
    """Linked rows: every arm aims at each grid point (``test``), then at each of the grid's
    cell centres (``holdout``), through its own model (``arms``)."""
    config = "+".join(specs)
    steps = []
    for s in (x for x in LINKED_SETS if x in sets):
        points = grid_targets(workspace, grid, s)
        per_arm = {name: _aim(arms[name], points, quantize, "aiming") for name in specs}
        steps += [Step(config, s, {n: per_arm[n][i] for n in specs},
                       (float(p[0]), float(p[1]))) for i, p in enumerate(points)]
    return steps


def check_plan(steps: Sequence[Step], specs: dict[str, ArmSpec]) -> None:
    """Every planned pulse inside the rig's pulse_limits, before the first move."""
    channels = {n: (0, 1) for n in specs}
    limits = {n: s.pulse_limits for n, s in specs.items()}
    for step in steps:
        try:
            check_limits(step.commands, channels, limits)
        except LimitError as exc:
            where = (f"target ({step.target[0]:g}, {step.target[1]:g})" if step.target
                     else f"a {step.set} grid point")
            raise LimitError(f"{where} needs pulses outside the limits: {exc}; shrink the "
                             f"workspace or widen pulse_limits in {RIG_FILE}") from None


def arm_models(specs: dict[str, ArmSpec], rows: Sequence[RecordedRow],
               log: Callable[[str], None] = lambda s: None
               ) -> tuple[dict[str, Arm], dict[str, str]]:
    """Each arm's model for the test rows: calibrated on its train rows if there are enough.

    Only train rows recorded before the first linked row count, so a resumed run plans the
    linked rows exactly as the interrupted one did.
    """
    from bayesrob.calibrate.arms import calibrate_arm
    from bayesrob.robot import Arm

    first_test = next((i for i, r in enumerate(rows) if "+" in r.config), len(rows))
    models, kinds = {}, {}
    for name, spec in specs.items():
        train = [r for r in rows[:first_test] if r.config == name and r.set == "train"]
        if len(train) >= N_ARM_PARAMS:
            u = np.array([r.commands[name] for r in train])
            d = np.array([r.observed for r in train])
            try:
                cal = calibrate_arm(spec, u, d)
            except (ValueError, np.linalg.LinAlgError) as exc:
                log(f"arm {name!r}: calibration failed ({exc}); aiming with the nominal model")
            else:
                models[name], kinds[name] = cal.arm, "calibrated"
                log(f"arm {name!r}: aiming the test rows with the model calibrated on "
                    f"{len(train)} train rows (train error {cal.train_error_mm:.2f} mm)")
                continue
        else:
            log(f"arm {name!r}: {len(train)} train rows are fewer than {N_ARM_PARAMS}; aiming "
                "the test rows with the nominal model")
        models[name], kinds[name] = Arm.nominal(spec), "nominal"
    return models, kinds


# ------------------------------------------------------------------------------ the file


@dataclass(frozen=True)
class RecordedRow:
    config: str
    set: str
    target: tuple[float, float] | None
    commands: dict[str, tuple[float, float]]
    observed: tuple[float, float]
    line: int


def _csv_line(fields: Sequence[str]) -> str:
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow(fields)
    return buf.getvalue()


class MeasurementLog:
    """``measurements.csv`` opened for appending rows that survive any interruption."""

    def __init__(self, path: str | Path, arm_names: Sequence[str], resume: bool = False,
                 check_only: bool = False):
        """Open (creating it with its header if needed); ``check_only`` validates, writes
        nothing and leaves the file closed."""
        self.path = Path(path)
        self.arm_names = list(arm_names)
        self.header = measurement_header(self.arm_names, approach=True)
        self.truncated_bytes = 0
        self.truncated_text = ""
        self.rows: list[RecordedRow] = []
        self._fd = -1
        data = self.path.read_bytes() if self.path.exists() else b""
        header_line = _csv_line(self.header).encode()
        if not resume and len([ln for ln in data.splitlines() if ln.strip()]) > 1:
            # Only a (possibly cut) header may be reused without --resume.
            raise RigError(f"{self.path}: already holds measurements; pass --resume to "
                           "continue that run, or move the file away to start afresh")
        if data and not data.endswith(b"\n"):
            # A row cut short by a kill or power loss: keep every complete line, drop the rest.
            keep = data.rfind(b"\n") + 1
            self.truncated_bytes = len(data) - keep
            self.truncated_text = data[keep:].decode("utf-8", "replace")
            data = data[:keep]
            if not check_only:
                os.truncate(self.path, keep)
        if data:
            self._parse(data)
        self.approach = self.header != measurement_header(self.arm_names)
        if check_only:
            return
        self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        if not data:
            try:
                self._write(header_line)
            except BaseException:
                self.close()
                raise
            _fsync_dir(self.path.parent)

    def _parse(self, data: bytes) -> None:
        try:
            text = data.decode("utf-8-sig")  # a BOM from a spreadsheet is not data
        except UnicodeDecodeError:
            raise RigError(f"{self.path}: not a UTF-8 text file") from None
        reader = csv.reader(io.StringIO(text, newline=""))
        header = [h.strip() for h in next(reader)]
        if header == measurement_header(self.arm_names):
            self.header = header  # written before rows recorded approach sides: keep its form
        if header != self.header:
            raise RigError(f"{self.path}: header {','.join(header)!r} does not match this rig's "
                           f"{','.join(self.header)!r}; resume needs the same rig.toml")
        idx = {h: i for i, h in enumerate(header)}
        rows = list(reader)
        for _, lineno, where, row in csv_records(self.path, header, rows,
                                                 range(2, len(rows) + 2)):
            config, set_ = row[idx["config"]].strip(), row[idx["set"]].strip()
            commands = {}
            for a in config.split("+"):
                if a not in self.arm_names:
                    raise RigError(f"{where}: config {config!r} names unknown arm {a!r}")
                commands[a] = (parse_number(row[idx[f"{a}_u1"]], where, f"{a}_u1"),
                               parse_number(row[idx[f"{a}_u2"]], where, f"{a}_u2"))
            tx, ty = row[idx["target_x"]].strip(), row[idx["target_y"]].strip()
            target = ((parse_number(tx, where, "target_x"), parse_number(ty, where, "target_y"))
                      if tx or ty else None)
            observed = (parse_number(row[idx["x"]], where, "x"),
                        parse_number(row[idx["y"]], where, "y"))
            self.rows.append(RecordedRow(config, set_, target, commands, observed, lineno))

    def _write(self, data: bytes) -> None:
        before = os.fstat(self._fd).st_size
        n = os.write(self._fd, data)  # one call: a row is on disk whole or not at all
        if n != len(data):
            os.ftruncate(self._fd, before)
            raise HardwareError(f"{self.path}: wrote {n} of {len(data)} bytes (disk full?); "
                                "the partial row was removed")
        os.fsync(self._fd)

    def append(self, fields: Sequence[str], parsed: RecordedRow | None = None) -> None:
        self._write(_csv_line(fields).encode())
        if parsed is not None:
            self.rows.append(parsed)

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> MeasurementLog:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _fsync_dir(directory: Path) -> None:
    # not supported on Windows: the file's own fsync still holds its rows
    with contextlib.suppress(OSError):
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


# ------------------------------------------------------------------------------ the run


@dataclass
class CollectResult:
    path: Path
    recorded: int = 0  # rows measured by this run
    skipped: int = 0  # rows found already recorded (resume)
    total: int = 0  # rows in the plan
    complete: bool = False
    truncated_bytes: int = 0
    models: dict[str, str] = field(default_factory=dict)  # arm -> calibrated | nominal
    notes: list[str] = field(default_factory=list)


def terminal_confirm(message: str) -> bool:
    """Ask at the terminal; Enter goes on, 'q' stops."""
    try:
        answer = input(f"{message}\n  press Enter when done, or q then Enter to stop: ")
    except EOFError:
        raise HardwareError(f"cannot ask '{message}': no terminal input (pass --yes to "
                            "confirm in advance)") from None
    return answer.strip().lower() not in ("q", "quit", "n", "no")


def _match(steps: Sequence[Step], pending: list[RecordedRow]) -> list[bool]:
    """Which steps are already recorded; consumes matched rows from ``pending``."""
    done = []
    for step in steps:
        hit = next((i for i, r in enumerate(pending) if step.matches(r)), None)
        if hit is not None:
            pending.pop(hit)
        done.append(hit is not None)
    return done


def _unplanned(rows: Sequence[RecordedRow], path: Path) -> RigError:
    r = rows[0]
    return RigError(f"{path}: line {r.line} ({r.config} {r.set}) is not part of this plan; "
                    "resume needs the same rig.toml, --grid, --plan and --protocol")


def match_recorded(specs: dict[str, ArmSpec], workspace: Workspace, grid: int,
                   quantize: Quantize, singles: Sequence[Step], do_test: bool,
                   rows: Sequence[RecordedRow], path: Path,
                   log: Callable[[str], None] = lambda s: None,
                   linked_sets: Sequence[str] = ("test",)
                   ) -> tuple[list[bool], list[Step] | None, list[bool], dict[str, str]]:
    """Which planned steps ``rows`` already hold; raises RigError for a row the plan lacks.

    Linked steps (of ``linked_sets``) are only planned here when linked rows were recorded
    (re-planned from the same train rows, so they match); otherwise they are planned when
    the run gets to them.
    """
    pending = list(rows)
    single_done = _match(singles, pending)
    tests: list[Step] | None = None
    test_done: list[bool] = []
    kinds: dict[str, str] = {}
    if do_test and any("+" in r.config for r in rows):
        models, kinds = arm_models(specs, rows, log)
        tests = linked_steps(specs, models, workspace, grid, quantize, linked_sets)
        test_done = _match(tests, pending)
    if pending:
        raise _unplanned(pending, path)
    return single_done, tests, test_done, kinds


def _planned(rig_dir: Path, grid: int, plan: Sequence[str], poses: str | Path | None,
             quantize: Quantize) -> tuple[dict[str, ArmSpec], Workspace, list[Step], list[str]]:
    """The rig's arms and workspace, its single-arm steps (checked against the pulse limits)
    and the linked sets the run will measure."""
    meta = load_rig_toml(rig_dir / RIG_FILE)
    specs, workspace = meta["arms"], meta["workspace"]
    if workspace is None and poses is None:
        raise RigError(f"{rig_dir / RIG_FILE}: collect needs 'workspace = [[x0, x1], [y0, y1]]' "
                       "to lay out the grid")
    singles = (plan_steps(poses, specs, quantize) if poses is not None else
               single_arm_steps(specs, workspace, grid, quantize, plan))
    check_plan(singles, specs)
    linked = [s for s in LINKED_SETS if s in plan] if len(specs) > 1 and poses is None else []
    return specs, workspace, singles, linked


def collect(rig_dir: str | Path, controller: ServoController, tracker: Tracker, *,
            grid: int = 4, plan: Sequence[str] = DEFAULT_PLAN, settle_s: float = 1.0,
            resume: bool = False, confirm: Callable[[str], bool] | None = None,
            progress: bool = False, log: Callable[[str], None] | None = None,
            poses: str | Path | None = None) -> CollectResult:
    """Run the paper's procedure on a connected controller and tracker; see the module doc.
    ``poses``: a ``poses.csv`` of ``bayesrob plan`` whose rows are measured instead, in its
    order (no grid, no linked rows; resume matches them as it matches the grid's).

    ``confirm`` is asked before each arm's rows (to put the tracker on it; only for a
    streaming tracker) and before the linked rows (to link the arms); ``None`` confirms
    everything. Returns what was done; raises HardwareError/RigError with every completed row
    already safe on disk.
    """
    from bayesrob.progress import progress as progress_report
    from bayesrob.sim.rigs import approach_sides

    log = log or _stderr
    rig_dir = Path(rig_dir)
    if grid < 2:
        raise ValueError(f"grid must be at least 2, got {grid}")
    specs, workspace, singles, linked_sets = _planned(rig_dir, grid, plan, poses,
                                                      controller.quantize)
    names = list(specs)
    for name in names:
        if name not in controller.channels:
            raise HardwareError(f"arm {name!r} has no channels on the controller")
        controller.limits[name] = specs[name].pulse_limits
    do_test = bool(linked_sets)
    n_test = sum(len(grid_targets(workspace, grid, s)) for s in linked_sets)
    if "test" in plan and len(names) < 2:
        log("one arm only: no linked test rows to collect")

    result = CollectResult(rig_dir / MEASUREMENTS_FILE, total=len(singles) + n_test)
    redone: list[str] = []  # labels of measurements discarded for dropped targets
    with MeasurementLog(result.path, names, resume) as mlog:
        result.truncated_bytes = mlog.truncated_bytes
        if mlog.truncated_bytes:
            log(f"{result.path}: removed a partial last row left by the interrupted run: "
                f"{mlog.truncated_text!r}")
        single_done, tests, test_done, models = match_recorded(
            specs, workspace, grid, controller.quantize, singles, do_test, mlog.rows,
            result.path, log, linked_sets)
        if models:
            result.models = models
        result.skipped = sum(single_done) + sum(test_done)
        if result.skipped:
            log(f"resuming: {result.skipped} of {result.total} rows already recorded")

        # No heartbeat: it would redraw over the operator's prompts between the sets.
        bar = progress_report(result.total, "collect", "rows", enabled=progress,
                              initial=result.skipped, heartbeat=False)

        # each arm's command before a row, from which its joints' approach sides follow; a
        # resumed run starts from the last recorded row's
        last = {a: u for r in mlog.rows for a, u in r.commands.items()}

        def run(step: Step, index: int) -> None:
            label = f"[{index + 1}/{result.total}] {step.describe()}"
            sides = {a: approach_sides(np.array([u]), last.get(a))[0]
                     for a, u in step.commands.items()}
            for attempt in range(1, ROW_TRIES + 1):
                controller.move_and_settle(step.commands)
                if settle_s > 0:
                    time.sleep(settle_s)
                observed = tracker.measure(label)
                # A controller that dropped its targets (an error sent the servos home or
                # limp) may have done so while the end point was read: measure the row again.
                dropped = controller.dropped_targets(step.commands)
                if dropped is None:
                    break
                if attempt == ROW_TRIES:
                    raise HardwareError(f"{label}: {dropped}, {ROW_TRIES} times in a row; the "
                                        "row was not recorded (check the servo power supply "
                                        "and the controller's serial line)")
                redone.append(label)
                log(f"{label}: {dropped}; measuring the row again")
                # the servos went home or limp before the targets were sent again: the side
                # each joint reached them from is no longer the previous command's
                sides = {a: np.zeros_like(v) for a, v in sides.items()}
            fields = format_row(names, step.config, step.set, step.target, step.commands,
                                observed, sides if mlog.approach else None)
            x = mlog.header.index("x")
            parsed = RecordedRow(step.config, step.set, step.target, step.commands,
                                 (float(fields[x]), float(fields[x + 1])), 0)
            mlog.append(fields, parsed)
            last.update(step.commands)
            result.recorded += 1
            bar.update(1)

        finished = False  # "done" on the progress line only when every row was taken
        try:
            index = 0
            for name in names:
                arm_steps = [(s, d) for s, d in zip(singles, single_done, strict=True)
                             if s.config == name]
                if confirm and isinstance(tracker, StreamTracker) and not all(
                        d for _, d in arm_steps):
                    if not confirm(f"Measuring arm {name!r}: put the tracker's marker on its end "
                                   "point and unlink the arms."):
                        result.notes.append("stopped by the operator")
                        return result
                for step, done in arm_steps:
                    if not done:
                        run(step, index)
                    index += 1
            if do_test:
                if tests is None:
                    models, result.models = arm_models(specs, mlog.rows, log)
                    tests = linked_steps(specs, models, workspace, grid, controller.quantize,
                                         linked_sets)
                    test_done = [False] * len(tests)
                check_plan(tests, specs)
                if not all(test_done):
                    if confirm and not confirm(f"Link the end points of {', '.join(names)} for "
                                               "the test rows."):
                        result.notes.append("stopped by the operator before the linked rows")
                        return result
                for step, done in zip(tests, test_done, strict=True):
                    if not done:
                        run(step, index)
                    index += 1
            finished = True
        except KeyboardInterrupt:
            log(f"interrupted: {len(mlog.rows)} rows are safe in {result.path}; continue with "
                "--resume")
            raise
        except HardwareError as exc:
            raise type(exc)(f"{exc}; {len(mlog.rows)} rows are safe in {result.path}, continue "
                            "with --resume") from exc
        finally:
            bar.close(done=finished)
    result.complete = True
    try:
        errs = controller.errors()
    except HardwareError as exc:  # every row is on disk; a last query failing changes nothing
        result.notes.append(f"could not read the controller's error flags: {exc}")
    else:
        if errs:
            result.notes.append(f"controller reported: {', '.join(errs)}")
    if redone:
        result.notes.append(f"controller: dropped its targets while measuring; {len(redone)} "
                            "measurements were discarded and their rows measured again")
    if controller.flagged_errors:
        result.notes.append("controller flagged errors while its outputs held their targets: "
                            f"{', '.join(sorted(set(controller.flagged_errors)))}")
    if isinstance(tracker, StreamTracker) and tracker.outliers:
        result.notes.append(f"tracker: {tracker.outliers} of {tracker.readings} readings were "
                            "rejected as far from their median before averaging")
    if isinstance(tracker, StreamTracker) and (tracker.bad_checksum or tracker.malformed):
        result.notes.append(f"tracker: {tracker.bad_checksum} lines with bad checksums and "
                            f"{tracker.malformed} malformed lines were ignored")
    if controller.resent_moves or controller.failed_queries:
        result.notes.append(f"controller: {controller.resent_moves} moves re-sent, "
                            f"{controller.failed_queries} queries retried")
    return result


# ------------------------------------------------------------------------------ ports


def _stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def controller_class(protocol: str) -> type[ServoController]:
    from bayesrob.hardware.maestro import Maestro
    from bayesrob.hardware.ssc32 import SSC32

    if protocol not in PROTOCOLS:
        raise ValueError(f"unknown protocol {protocol!r} (choose from {', '.join(PROTOCOLS)})")
    return SSC32 if protocol == "ssc32" else Maestro


def open_controller(protocol: str, port: str, channels: dict[str, tuple[int, int]],
                    limits: dict, *, baud: int = 9600, maestro_protocol: str = "compact",
                    device_number: int = 12,
                    speed_us_per_s: float | None = DEFAULT_SPEED_US_PER_S,
                    timeout_s: float = DEFAULT_TIMEOUT_S,
                    retries: int = DEFAULT_RETRIES, maestro_model: str | None = None,
                    auto_baud: bool = False) -> ServoController:
    """Open the servo port exclusively and check that the controller answers."""
    cls = controller_class(protocol)
    maestro = {} if protocol == "ssc32" else {"protocol": maestro_protocol,
                                              "device": device_number, "model": maestro_model,
                                              "auto_baud": auto_baud}
    link = SerialLink(open_port(port, baud, timeout_s, "servo"), "servo")
    try:
        ctl = cls(link, channels, limits, speed_us_per_s=speed_us_per_s, retries=retries,
                  **maestro)
        ctl.description = ctl.connect()
    except BaseException:
        link.close()
        raise
    return ctl


def collect_on_ports(rig_dir: str | Path, *, servo_port: str, protocol: str,
                     channels: dict[str, tuple[int, int]], tracker_port: str | None = None,
                     manual: bool = False, grid: int = 4, plan: Sequence[str] = DEFAULT_PLAN,
                     settle_s: float = 1.0, resume: bool = False,
                     tracker_format: TrackerFormat = "pxyt", tracker_baud: int = 115200,
                     samples: int = 5, timeout_s: float = DEFAULT_TIMEOUT_S,
                     maestro_model: str | None = None,
                     confirm: Callable[[str], bool] | None = terminal_confirm,
                     progress: bool = False, log: Callable[[str], None] | None = None,
                     poses: str | Path | None = None, **controller_options) -> CollectResult:
    """What ``bayesrob collect`` does: check the arguments, open the ports, run :func:`collect`
    (``controller_options``: :func:`open_controller`'s).

    Everything that can be checked without hardware (rig.toml, channels, the planned pulses
    against pulse_limits) is checked before a port is opened, so a bad request sends nothing.
    """
    from bayesrob.hardware import maestro, ssc32

    if (tracker_port is None) == (not manual):
        raise ArgumentError("give either a tracker port or manual entry")
    rig_dir = Path(rig_dir)
    specs = load_rig_toml(rig_dir / RIG_FILE)["arms"]
    cls = controller_class(protocol)
    if protocol == "ssc32":
        check_channels(channels, specs, ssc32.MAX_CHANNELS, "an SSC-32")
    else:
        check_channels(channels, specs, maestro.n_channels(maestro_model),
                       maestro.describe_model(maestro_model))
    quantize = functools.partial(quantize_us, resolution_us=cls.resolution_us)
    specs, workspace, singles, linked = _planned(rig_dir, grid, plan, poses, quantize)
    # Refuse to touch an existing file without --resume, or to resume a different plan,
    # before any port is opened.
    existing = MeasurementLog(rig_dir / MEASUREMENTS_FILE, list(specs), resume,
                              check_only=True)
    if existing.rows:
        match_recorded(specs, workspace, grid, quantize, singles, bool(linked), existing.rows,
                       existing.path, linked_sets=linked)
    limits = {n: s.pulse_limits for n, s in specs.items()}
    controller = open_controller(protocol, servo_port, channels, limits, timeout_s=timeout_s,
                                 maestro_model=maestro_model, **controller_options)
    (log or _stderr)(f"connected: {controller.description}")
    tlink = None
    try:
        if manual:
            tracker: Tracker = ManualTracker()
        else:
            assert tracker_port is not None
            tlink = SerialLink(open_port(tracker_port, tracker_baud, timeout_s, "tracker"),
                               "tracker")
            tracker = StreamTracker(tlink, tracker_format, samples,
                                    timeout_s=max(3.0, 10 * timeout_s))
        return collect(rig_dir, controller, tracker, grid=grid, plan=plan, settle_s=settle_s,
                       resume=resume, confirm=confirm, progress=progress, log=log, poses=poses)
    finally:
        controller.close()
        if tlink is not None:
            tlink.close()
