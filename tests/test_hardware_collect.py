"""``bayesrob collect`` against the simulated device, through real pseudo-terminal serial ports.

The device (``SimDevice``) answers as a Maestro or an SSC-32 and streams tracker lines, with the
end points of the physical simulator; nothing here is a mock. Grids are small (2 or 3) and
settle times zero so the whole file runs in well under a minute.
"""

from __future__ import annotations

import contextlib
import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import serial

from bayesrob.cli import main
from bayesrob.data.rig import RigError, dump_toml, load_measurements, load_rig, load_rig_toml
from bayesrob.data.rig import rig_toml_dict as _rig_toml_dict
from bayesrob.hardware import DisconnectedError, HardwareError, LimitError
from bayesrob.hardware.collect import (
    MeasurementLog,
    collect,
    collect_on_ports,
    linked_steps,
    open_controller,
    single_arm_steps,
)
from bayesrob.hardware.controller import SerialLink, open_port, quantize_us
from bayesrob.hardware.simdevice import Faults, SimDevice
from bayesrob.hardware.tracker import ManualTracker, StreamTracker
from bayesrob.robot import Arm
from bayesrob.sim.equilibrium import PhysicalRig
from bayesrob.sim.rigs import nominal_specs
from bayesrob.sim.truth import paper_truth

CHANNELS = {"top": (0, 1), "bottom": (2, 3)}
CHANNEL_ARGS = ["top=0,1", "bottom=2,3"]
# Fast enough for CI, slow enough that the controllers really ramp (a few ms per move).
FAST = dict(settle_s=0.0, speed_us_per_s=50000.0, timeout_s=1.0, confirm=None, progress=False)
PROTOCOLS = [("maestro", "compact"), ("maestro", "pololu"), ("ssc32", "compact")]
RESOLUTION = {"maestro": 0.25, "ssc32": 1.0}


# ------------------------------------------------------------------------------ fixtures


@pytest.fixture(scope="module")
def sim_rig(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """truth.toml and rig.toml of the paper's clean two-arm rig; no measurements."""
    truth = paper_truth((), seed=3, grid=3)
    d = tmp_path_factory.mktemp("hw_sim_rig")
    specs = nominal_specs(truth, np.random.default_rng(truth.seed))
    (d / "rig.toml").write_text(dump_toml(_rig_toml_dict(truth.name, specs, truth.gravity,
                                                         truth.workspace)))
    (d / "truth.toml").write_text(truth.to_toml())
    return d


@pytest.fixture(scope="module")
def plant(sim_rig: Path) -> PhysicalRig:
    # One plant for the module: its solvers compile once. Each device reseeds its noise.
    return PhysicalRig.from_rig_dir(sim_rig)


@pytest.fixture
def rig_dir(sim_rig: Path, tmp_path: Path) -> Path:
    """A fresh collection directory: the rig's rig.toml only, as a user starts."""
    d = tmp_path / "rig"
    d.mkdir()
    shutil.copy(sim_rig / "rig.toml", d / "rig.toml")
    return d


@contextlib.contextmanager
def device(plant: PhysicalRig, protocol: str = "maestro", seed: int = 0, **kw):
    """A served SimDevice whose physics noise starts from ``seed``, like a fresh process."""
    plant.rng = np.random.default_rng(seed)
    kw.setdefault("tracker_rate_hz", 500.0)
    kw.setdefault("tracker_noise_mm", 0.0)
    dev = SimDevice(plant, protocol, seed=seed, **kw)
    with dev:
        yield dev


def run(dev: SimDevice, rig_dir: Path, protocol: str = "maestro", **kw):
    logs: list[str] = []
    args = {**FAST, **kw}
    res = collect_on_ports(rig_dir, servo_port=dev.servo_port, protocol=protocol,
                           channels=CHANNELS, tracker_port=dev.tracker_port, log=logs.append,
                           **args)
    res.logs = logs  # type: ignore[attr-defined]
    return res


def open_pair(dev: SimDevice, protocol: str = "maestro", timeout_s: float = 1.0,
              retries: int = 5, maestro_protocol: str = "compact"):
    ctl = open_controller(protocol, dev.servo_port, CHANNELS,
                          {n: arm.pulse_limits for n, arm in dev.truth.arms.items()},
                          speed_us_per_s=50000.0, timeout_s=timeout_s, retries=retries,
                          maestro_protocol=maestro_protocol)
    link = SerialLink(open_port(dev.tracker_port, 115200, timeout_s, "tracker"), "tracker")
    return ctl, StreamTracker(link, "pxyt", 5, timeout_s=3.0)


class Watching:
    """A tracker wrapper that notes, at each measurement, the device's pose, and can act."""

    def __init__(self, tracker, dev: SimDevice, after=None):
        self.tracker, self.dev, self.after = tracker, dev, after
        self.seen: list[tuple[dict, np.ndarray, np.ndarray]] = []

    def measure(self, label: str = "") -> np.ndarray:
        if self.after is not None:
            self.after(len(self.seen))
        d = self.tracker.measure(label)
        pose = self.dev.poses[-1]
        self.seen.append((pose.commands, pose.end_point, d))
        return d


def keys(rig_dir: Path) -> list[tuple[str, ...]]:
    """Each row's config, set, target and commands, as text: what resume must reproduce."""
    with (rig_dir / "measurements.csv").open(newline="") as fh:
        rows = list(csv.reader(fh))
    x = rows[0].index("x")
    return [tuple(r[:x]) for r in rows[1:] if r]


def planned(rig_dir: Path, grid: int, protocol: str = "maestro",
            sets=("train", "validation", "test")) -> list[tuple[str, ...]]:
    """The rows a run with nominal test commands (grid 2: too few train rows) must produce."""
    from bayesrob.data.rig import format_row

    meta = load_rig_toml(rig_dir / "rig.toml")
    specs = meta["arms"]
    q = lambda u: quantize_us(u, RESOLUTION[protocol])  # noqa: E731
    steps = single_arm_steps(specs, meta["workspace"], grid, q, sets)
    if "test" in sets:
        steps += linked_steps(specs, {n: Arm.nominal(s) for n, s in specs.items()},
                              meta["workspace"], grid, q)
    return [tuple(format_row(list(specs), s.config, s.set, s.target, s.commands, (0, 0))[:-2])
            for s in steps]


# ------------------------------------------------------------------------------ the procedure


@pytest.mark.parametrize(("protocol", "wire"), PROTOCOLS)
def test_collect_produces_a_rig_that_calibrates(plant, rig_dir, protocol, wire) -> None:
    with device(plant, protocol, seed=11) as dev:
        res = run(dev, rig_dir, protocol, grid=3, maestro_protocol=wire)
        poses = list(dev.poses)
        received = dev.received
    assert res.complete and (res.recorded, res.skipped, res.total) == (45, 0, 45)
    assert res.models == {"top": "calibrated", "bottom": "calibrated"}
    rig = load_rig(rig_dir)
    m = rig.measurements
    assert m.config.tolist() == ["top"] * 18 + ["bottom"] * 18 + ["top+bottom"] * 9
    assert m.set.tolist() == (["train"] * 9 + ["validation"] * 9) * 2 + ["test"] * 9
    # Validation repeats the train commands exactly.
    for arm in ("top", "bottom"):
        assert np.array_equal(rig.rows(arm, "train")[0], rig.rows(arm, "validation")[0])
    # The device settled each row's commands, linked exactly for the test rows.
    assert [p.arms for p in poses] == [("top",)] * 18 + [("bottom",)] * 18 + \
        [("top", "bottom")] * 9
    for i, pose in enumerate(poses):
        for arm, u in pose.commands.items():
            assert np.allclose(m.commands[arm][i], u)
        assert np.allclose(m.observed[i], pose.end_point, atol=1e-3)
    first = {"compact": b"\xa1", "pololu": bytes([0xAA, 12, 0x21])}[wire] \
        if protocol == "maestro" else b"VER\r"
    assert received.startswith(first)
    report = rig_dir / "calibration.json"
    assert main(["calibrate", str(rig_dir), "--json", str(report)]) == 0
    acc = json.loads(report.read_text())["accuracy"]
    for arm in ("top", "bottom"):
        assert 0.2 < acc[arm]["validation"]["mean_mm"] < 1.2
    assert 0.1 < acc["top+bottom"]["test"]["mean_mm"] < 1.5


def test_rows_are_written_whole_one_write_each_and_fsynced(plant, rig_dir, monkeypatch) -> None:
    writes: list[bytes] = []
    syncs: list[int] = []
    real_write, real_fsync = os.write, os.fsync

    def spy_write(fd, data):
        if b"train" in bytes(data) or b"config" in bytes(data):
            writes.append(bytes(data))
        return real_write(fd, data)

    def spy_fsync(fd):
        syncs.append(fd)
        return real_fsync(fd)

    monkeypatch.setattr(os, "write", spy_write)
    monkeypatch.setattr(os, "fsync", spy_fsync)
    with device(plant) as dev:
        res = run(dev, rig_dir, grid=2, plan=("train",))
    assert res.recorded == 8
    assert len(writes) == 9  # the header, then one write per row
    assert all(w.endswith(b"\n") and w.count(b"\n") == 1 for w in writes)
    assert len(syncs) >= 9
    assert b"".join(writes) == (rig_dir / "measurements.csv").read_bytes()


def test_interrupted_run_keeps_every_row_and_resume_matches_an_uninterrupted_run(
        plant, rig_dir, tmp_path, capsys) -> None:
    ref = tmp_path / "ref"
    ref.mkdir()
    shutil.copy(rig_dir / "rig.toml", ref / "rig.toml")
    with device(plant, seed=5) as dev:
        run(dev, ref, grid=2)

    def ctrl_c(n: int) -> None:
        if n == 6:
            raise KeyboardInterrupt

    logs: list[str] = []
    with device(plant, seed=5) as dev:
        ctl, tracker = open_pair(dev)
        with pytest.raises(KeyboardInterrupt):
            collect(rig_dir, ctl, Watching(tracker, dev, ctrl_c), grid=2, settle_s=0,
                    log=logs.append, progress=True)
        ctl.close()
        tracker.link.close()
        assert any("6 rows are safe" in s and "--resume" in s for s in logs)
        # the progress report stops where the rows did: an interrupted run is not "done"
        lines = [x for x in capsys.readouterr().err.splitlines() if x.startswith("collect:")]
        assert lines and not any(x.endswith("done") for x in lines), lines
        assert len(load_measurements(rig_dir / "measurements.csv",
                                     load_rig_toml(rig_dir / "rig.toml")["arms"])) == 6
        assert keys(rig_dir) == keys(ref)[:6]
        res = run(dev, rig_dir, grid=2, resume=True)
    assert (res.skipped, res.recorded, res.total) == (6, 14, 20)
    assert keys(rig_dir) == keys(ref) == planned(rig_dir, 2)


def test_resume_drops_a_partial_last_line(plant, rig_dir) -> None:
    with device(plant) as dev:
        run(dev, rig_dir, grid=2, plan=("train",))
        before = (rig_dir / "measurements.csv").read_bytes()
        with (rig_dir / "measurements.csv").open("ab") as fh:
            fh.write(b"bottom,train,,,1532.25,14")  # power lost mid-row
        res = run(dev, rig_dir, grid=2, plan=("train", "validation"), resume=True)
    assert res.truncated_bytes == len(b"bottom,train,,,1532.25,14")
    assert any("partial last row" in s for s in res.logs)
    assert (rig_dir / "measurements.csv").read_bytes().startswith(before)
    assert (res.skipped, res.recorded) == (8, 8)
    assert sorted(keys(rig_dir)) == sorted(planned(rig_dir, 2, sets=("train", "validation")))


def test_existing_rows_are_never_touched_without_resume_or_with_another_plan(
        plant, rig_dir) -> None:
    with device(plant) as dev:
        run(dev, rig_dir, grid=2, plan=("train",))
        before = (rig_dir / "measurements.csv").read_bytes()
        n_received = len(dev.received)
        with pytest.raises(RigError, match="already holds measurements.*--resume"):
            run(dev, rig_dir, grid=2)
        with pytest.raises(RigError, match="line 2 .* not part of this plan"):
            run(dev, rig_dir, grid=2, plan=("validation",), resume=True)
        with pytest.raises(RigError, match="line 2 .* not part of this plan"):
            run(dev, rig_dir, "ssc32", grid=2, resume=True)  # whole microseconds
        time.sleep(0.05)
        assert len(dev.received) == n_received  # refused before a port was opened
    assert (rig_dir / "measurements.csv").read_bytes() == before
    with pytest.raises(RigError, match="header"):
        MeasurementLog(rig_dir / "measurements.csv", ["top", "left"], resume=True)


# ------------------------------------------------------------------------------ faults


def _check_integrity(watch: Watching, rig_dir: Path, max_redone: int = 3) -> None:
    """Every recorded row was measured at the pose of its own commands, and reads true.

    A row measured again (the read-back after the measurement did not confirm the targets,
    as damaged replies on a loaded machine can make it) counts by its last measurement.
    """
    rig = load_rig(rig_dir, min_train_rows=0)
    last = [s for i, s in enumerate(watch.seen)
            if i + 1 == len(watch.seen) or watch.seen[i + 1][0] != s[0]]
    assert len(watch.seen) - len(last) <= max_redone
    assert len(last) == len(rig.measurements)
    for i, (commands, true_d, measured) in enumerate(last):
        for arm, u in commands.items():
            assert np.allclose(rig.measurements.commands[arm][i], u)
        assert np.allclose(measured, true_d, atol=2e-3)
        assert np.allclose(rig.measurements.observed[i], measured, atol=1e-4)


@pytest.mark.parametrize(("protocol", "faults", "exercised"), [
    ("maestro", Faults(drop_rate=0.03), "queries"),
    ("ssc32", Faults(drop_rate=0.03), "queries"),
    ("maestro", Faults(garble_rate=0.03), "tracker"),
    ("ssc32", Faults(garble_rate=0.03), "tracker"),
    ("maestro", Faults(rx_garble_rate=0.03), "controller"),
    ("maestro", Faults(bad_checksum_rate=0.3), "checksum"),
    ("maestro", Faults(reply_delay_s=0.02), None),
], ids=["drop-maestro", "drop-ssc32", "garble-maestro", "garble-ssc32", "rx-garble-maestro",
        "bad-checksum", "slow-replies"])
def test_collect_survives_faults_without_a_wrong_row(plant, rig_dir, protocol, faults,
                                                     exercised) -> None:
    with device(plant, protocol, seed=7, faults=faults, tracker_noise_mm=0.0) as dev:
        ctl, tracker = open_pair(dev, protocol, timeout_s=0.15)
        watch = Watching(tracker, dev)
        try:
            res = collect(rig_dir, ctl, watch, grid=2, settle_s=0, log=lambda s: None)
        finally:
            ctl.close()
            tracker.link.close()
    assert res.complete and res.recorded == 20
    assert keys(rig_dir) == planned(rig_dir, 2, protocol)
    _check_integrity(watch, rig_dir)
    if exercised == "queries":
        # How often the host polls depends on the machine's load, so whether a 3% drop hit a
        # reply at all is not fixed by the seed; every reply the device damaged must have
        # been noticed and retried by the host.
        assert dev.corrupted_replies == 0 or ctl.failed_queries > 0
    elif exercised == "tracker":
        assert tracker.bad_checksum + tracker.malformed > 0
    elif exercised == "controller":
        assert ctl.failed_queries + ctl.resent_moves > 0
    elif exercised == "checksum":
        assert tracker.bad_checksum > 0


def test_replies_slower_than_the_timeout_stop_the_run_cleanly(plant, rig_dir) -> None:
    def slow_down(n: int) -> None:
        if n == 3:
            dev.faults = Faults(reply_delay_s=0.4)

    with device(plant) as dev:
        ctl, tracker = open_pair(dev, timeout_s=0.1, retries=2)
        # The replies slow down as the 4th row is measured: the check that the controller
        # still holds the row's targets gets no answer, so that row is not recorded.
        with pytest.raises(HardwareError, match=r"Get Errors got 0 of 2 reply bytes within "
                                                r"0.1 s.*3 rows are safe"):
            collect(rig_dir, ctl, Watching(tracker, dev, slow_down), grid=2, settle_s=0,
                    log=lambda s: None)
        ctl.close()
        tracker.link.close()
        assert keys(rig_dir) == planned(rig_dir, 2)[:3]
        dev.faults = Faults()
        time.sleep(1.0)  # let the device work off the requests it was sleeping on
        res = run(dev, rig_dir, grid=2, resume=True)
    assert (res.skipped, res.recorded) == (3, 17)
    assert keys(rig_dir) == planned(rig_dir, 2)


@pytest.mark.parametrize("protocol", ["maestro", "ssc32"])
def test_disconnect_is_reported_and_resume_completes(plant, rig_dir, protocol) -> None:
    with device(plant, protocol, faults=Faults(disconnect_after=40)) as dev:
        with pytest.raises(DisconnectedError, match=r"lost the servo port.*rows are safe"):
            run(dev, rig_dir, protocol, grid=2)
        assert dev.disconnected
    n = len(keys(rig_dir))
    assert 1 <= n < 20
    assert keys(rig_dir) == planned(rig_dir, 2, protocol)[:n]
    with device(plant, protocol) as dev:  # plugged in again: new ports
        res = run(dev, rig_dir, protocol, grid=2, resume=True)
    assert (res.skipped, res.recorded) == (n, 20 - n)
    assert keys(rig_dir) == planned(rig_dir, 2, protocol)


def test_plain_tracker_lines(plant, rig_dir) -> None:
    with device(plant, tracker_format="plain") as dev:
        res = run(dev, rig_dir, grid=2, plan=("train",), tracker_format="plain")
        poses = list(dev.poses)
    assert res.recorded == 8
    obs = load_rig(rig_dir, min_train_rows=0).measurements.observed
    assert np.allclose(obs, [p.end_point for p in poses], atol=1e-3)


# ------------------------------------------------------------------------------ safety


def test_a_plan_outside_the_pulse_limits_sends_nothing(plant, rig_dir) -> None:
    text = (rig_dir / "rig.toml").read_text()
    narrow = text.replace("pulse_limits = [[600.0, 2400.0], [600.0, 2400.0]]",
                          "pulse_limits = [[1300.0, 1700.0], [1300.0, 1700.0]]")
    assert narrow != text
    (rig_dir / "rig.toml").write_text(narrow)
    with device(plant) as dev:
        with pytest.raises(LimitError, match="outside the limits"):
            run(dev, rig_dir, grid=3)
        time.sleep(0.1)
        assert dev.received == b""
    assert not (rig_dir / "measurements.csv").exists()


def test_the_link_prompt_can_stop_the_run_before_linked_rows(plant, rig_dir) -> None:
    asked: list[str] = []

    def confirm(message: str) -> bool:
        asked.append(message)
        return "Link" not in message

    with device(plant) as dev:
        res = run(dev, rig_dir, grid=2, confirm=confirm)
        poses = list(dev.poses)
    assert not res.complete and res.recorded == 16
    assert [m.split(":")[0] for m in asked] == ["Measuring arm 'top'", "Measuring arm 'bottom'",
                                                "Link the end points of top, bottom for the test "
                                                "rows."]
    assert all(len(p.arms) == 1 for p in poses)  # no linked move was sent


@pytest.mark.parametrize(("linked", "move", "settled"), [
    ("auto", ("top",), ("top",)), ("auto", ("top", "bottom"), ("top", "bottom")),
    ("always", ("bottom",), ("top", "bottom")), ("never", ("top", "bottom"), ("top",))])
def test_sim_device_linking_modes(plant, linked, move, settled) -> None:
    with device(plant, linked=linked) as dev:
        ctl, tracker = open_pair(dev)
        try:
            u = {"top": (1500.0, 1600.0), "bottom": (1450.0, 1350.0)}
            ctl.move_and_settle({a: u[a] for a in move})
            free = {a: plant.end_point({a: u[a] if a in move else dev_home(dev, a)},
                                       noise=False) for a in ("top", "bottom")}
            d = tracker.measure()
        finally:
            ctl.close()
            tracker.link.close()
        assert dev.poses[-1].arms == settled
    if len(settled) == 1:
        assert np.allclose(d, free[settled[0]], atol=3.0)  # noise only
    else:  # linked: a tug of war between the arms, not either arm's free end point
        assert min(np.linalg.norm(d - free["top"]), np.linalg.norm(d - free["bottom"])) > 3.0


def dev_home(dev: SimDevice, arm: str) -> tuple[float, float]:
    c1, c2 = dev.channels[arm]
    return dev.home_us[c1], dev.home_us[c2]


def test_maestro_go_home_and_errors_on_the_sim_device(plant) -> None:
    with device(plant) as dev:
        ctl, tracker = open_pair(dev)
        try:
            ctl.move_and_settle({"top": (1500.0, 1600.25)})
            assert ctl.read_positions(["top"]) == {"top": (1500.0, 1600.25)}
            ctl.home()
            time.sleep(0.05)
            assert ctl.read_positions(["top"]) == {"top": dev_home(dev, "top")}
            ctl.link.write(bytes([0x84, 0x00, 0x70]))  # a Set Target cut short ...
            assert not ctl.is_moving()  # ... by the next command byte
            assert ctl.errors() == ["serial protocol error"]
            assert ctl.errors() == []  # reading clears them
            time.sleep(0.05)
            before = dev.received
            with pytest.raises(LimitError):
                ctl.move_and_settle({"top": (1500.0, 2400.25)})  # rig limit 2400
            time.sleep(0.05)
            assert dev.received == before
        finally:
            ctl.close()
            tracker.link.close()


# ------------------------------------------------------------------------------ manual entry


def test_manual_entry_records_only_valid_answers(plant, rig_dir) -> None:
    typed: list[str] = []
    with device(plant) as dev:
        def operator(prompt: str) -> str:
            if len(typed) % 2 == 0:
                typed.append("12.5")  # one number: asked again
                return typed[-1]
            x, y = dev.end_point
            typed.append(f"{x:.2f} {y:.2f}")
            return typed[-1]

        ctl, _ = open_pair(dev)
        tracker = ManualTracker(operator, lambda s: None)
        res = collect(rig_dir, ctl, tracker, grid=2, plan=("train",), settle_s=0,
                      log=lambda s: None)
        ctl.close()
    assert res.recorded == 8 and tracker.rejected == 8
    obs = load_rig(rig_dir, min_train_rows=0).measurements.observed
    assert obs.tolist() == [[float(v) for v in t.split()] for t in typed[1::2]]


def test_manual_entry_from_the_command_line(plant, rig_dir, monkeypatch, capsys) -> None:
    answers = ["", "abc def", "101 202", "nan 4", "103.5 204", "105 206", "107 208", "109 210",
               "111 212", "113 214", "115 216"]
    monkeypatch.setattr(sys, "stdin", __import__("io").StringIO("\n".join(answers) + "\n"))
    with device(plant) as dev:
        code = main(["collect", str(rig_dir), "--servo-port", dev.servo_port, "--protocol",
                     "maestro", "--channels", *CHANNEL_ARGS, "--manual", "--grid", "2",
                     "--plan", "train", "--settle", "0", "--speed", "50000", "--yes"])
    assert code == 0
    err = capsys.readouterr().err
    assert err.count("not recorded") == 3
    obs = load_rig(rig_dir, min_train_rows=0).measurements.observed
    assert obs.tolist() == [[101, 202], [103.5, 204], [105, 206], [107, 208], [109, 210],
                            [111, 212], [113, 214], [115, 216]]


# ------------------------------------------------------------------------------ command line


def _collect_argv(rig_dir: Path, servo: str, tracker: str, *extra: str) -> list[str]:
    return ["collect", str(rig_dir), "--servo-port", servo, "--protocol", "maestro",
            "--tracker-port", tracker, "--settle", "0", "--speed", "50000", "--yes", *extra]


@pytest.mark.parametrize(("channels", "message"), [
    (["top=0,1", "middle=2,3"], "unknown arm 'middle'"),
    (["top=0,1", "bottom=2,30"], "channel 30 of arm 'bottom' does not exist"),
    (["top=0,1", "bottom=1,2"], "channel 1 is given to both 'top' and 'bottom'"),
    (["top=0", "bottom=2,3"], "arm 'top' needs two channel numbers"),
    (["top=0,1"], "no channels given for arm 'bottom'"),
])
def test_bad_channels_are_one_line_errors(plant, rig_dir, capsys, channels, message) -> None:
    with device(plant) as dev:
        argv = _collect_argv(rig_dir, dev.servo_port, dev.tracker_port)
        code = main([*argv, "--channels", *channels])
        time.sleep(0.05)
        assert dev.received == b""
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("bayesrob collect: error:") and message in err
    assert not (rig_dir / "measurements.csv").exists()


def test_bad_ports_and_plans_are_one_line_errors(plant, rig_dir, capsys, tmp_path) -> None:
    with device(plant) as dev:
        cases = [
            (_collect_argv(rig_dir, "/dev/no-such-servo", dev.tracker_port), "no such device"),
            (_collect_argv(rig_dir, dev.servo_port, dev.tracker_port, "--plan", "train,tset"),
             "unknown set 'tset'"),
            (_collect_argv(tmp_path / "missing", dev.servo_port, dev.tracker_port),
             "file not found"),
        ]
        with serial.Serial(dev.servo_port, exclusive=True):
            cases.append((_collect_argv(rig_dir, dev.servo_port, dev.tracker_port),
                          "cannot open it"))  # another program holds the port
            for argv, message in cases:
                code = main([*argv, "--channels", *CHANNEL_ARGS])
                err = capsys.readouterr().err
                assert code == 2, argv
                assert err.count("\n") == 1 and message in err, err
        time.sleep(0.05)
        assert dev.received == b""


def test_sim_device_command_serves_both_ports_and_logs_bytes(sim_rig, tmp_path) -> None:
    log = tmp_path / "bytes.bin"
    proc = subprocess.Popen([sys.executable, "-m", "bayesrob", "sim-device", str(sim_rig),
                             "--protocol", "ssc32", "--byte-log", str(log), "--tracker-rate",
                             "200"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        lines = [proc.stdout.readline() for _ in range(2)]
        assert lines[0].startswith("servo: /dev/") and lines[1].startswith("tracker: /dev/")
        servo_path, tracker_path = (ln.split(": ", 1)[1].strip() for ln in lines)
        with serial.Serial(servo_path, timeout=2) as s, serial.Serial(tracker_path,
                                                                     timeout=2) as t:
            s.write(b"VER\r")
            assert s.read_until(b"\r").startswith(b"SSC32")
            s.write(b"#0P1500#1P1610\rQP0\rQP1\r")
            assert s.read(2) == bytes([150, 161])
            t.reset_input_buffer()
            t.readline()
            line = t.readline()
            assert line.startswith(b"$PXYT,") and line.endswith(b"\r\n")
        assert log.read_bytes() == b"VER\r#0P1500#1P1610\rQP0\rQP1\r"
    finally:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err


def test_sim_device_without_truth_is_a_one_line_error(rig_dir, capsys) -> None:
    assert main(["sim-device", str(rig_dir), "--protocol", "maestro"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "truth.toml: file not found" in err


def test_killed_collect_resumes_to_the_rows_of_an_uninterrupted_run(plant, rig_dir,
                                                                    tmp_path) -> None:
    """SIGKILL a collect process during the linked rows, then --resume.

    Grid 3 gives each arm enough train rows to calibrate, so the linked rows' commands come
    from the recorded train rows; the resumed run must plan exactly the same ones.
    """
    ref = tmp_path / "ref"
    ref.mkdir()
    shutil.copy(rig_dir / "rig.toml", ref / "rig.toml")
    with device(plant, seed=21) as dev:
        assert run(dev, ref, grid=3).models == {"top": "calibrated", "bottom": "calibrated"}

    csv_path = rig_dir / "measurements.csv"
    with device(plant, seed=21) as dev:
        argv = _collect_argv(rig_dir, dev.servo_port, dev.tracker_port, "--grid", "3",
                             "--timeout", "1", "--channels", *CHANNEL_ARGS)
        proc = subprocess.Popen([sys.executable, "-m", "bayesrob", *argv],
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        try:
            deadline = time.monotonic() + 90
            while time.monotonic() < deadline and proc.poll() is None:
                if csv_path.exists() and csv_path.read_bytes().count(b"\n") >= 1 + 36 + 2:
                    break
                time.sleep(0.005)
            assert proc.poll() is None, proc.stderr.read().decode()
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=10)
        finally:
            if proc.poll() is None:
                proc.kill()
        n = len(keys(rig_dir))
        assert 38 <= n < 45
        assert keys(rig_dir) == keys(ref)[:n]
        assert main([*argv, "--resume"]) == 0
    assert keys(rig_dir) == keys(ref)
    assert main(["calibrate", str(rig_dir)]) == 0


# ------------------------------------------------------------------------------ Maestro quirks


def _on_target(dev: SimDevice, commands: dict) -> bool:
    """Whether the device outputs exactly ``commands`` right now (not mid-ramp)."""
    now = time.monotonic()
    return all(dev._outputs[ch].position(now) == u for arm, pair in commands.items()
               for ch, u in zip(dev.channels[arm], pair, strict=True))


class Arrival(Watching):
    """Also notes, at each measurement, whether the outputs had reached the row's targets."""

    def __init__(self, tracker, dev: SimDevice, after=None):
        super().__init__(tracker, dev, after)
        self.arrived: list[bool] = []

    def measure(self, label: str = "") -> np.ndarray:
        self.arrived.append(_on_target(self.dev, self.dev.poses[-1].commands))
        return super().measure(label)


def test_micro_maestro_moving_state_bug_does_not_stop_or_fool_collect(plant, rig_dir) -> None:
    # 2000 us/s: the plan's moves (up to ~900 us) ramp for up to ~0.45 s, many polls long.
    with device(plant, seed=4, moving_state_bug=True) as dev:
        ctl, tracker = open_pair(dev)
        ctl.speed_us_per_s = 2000.0
        ctl.connect()  # sends the new speed limit
        watch = Arrival(tracker, dev)
        try:
            res = collect(rig_dir, ctl, watch, grid=2, plan=("train",), settle_s=0,
                          log=lambda s: None)
        finally:
            ctl.close()
            tracker.link.close()
        assert dev.false_idle_answers > 0  # the bug answered 0 during ramps
    assert res.complete and res.recorded == 8
    assert keys(rig_dir) == planned(rig_dir, 2, sets=("train",))
    assert all(watch.arrived)  # every row measured only after its outputs arrived
    _check_integrity(watch, rig_dir)


def test_trusting_the_micro_moving_state_fails_as_the_issue_describes(plant) -> None:
    """The contrast: a host that believes Get Moving State gives up on a healthy controller."""
    with device(plant, moving_state_bug=True) as dev:
        ctl, tracker = open_pair(dev)
        ctl.speed_us_per_s = 300.0
        ctl.connect()
        try:
            ctl.move_and_settle({"top": (1500.0, 1500.0)})
            ctl.moving_state_reliable = True  # the old behaviour
            # 2 s ramps: the 5 tries (two polls each) end long before, even on a loaded machine.
            with pytest.raises(HardwareError, match=r"instead of the commanded .* after 5 tries"):
                ctl.move_and_settle({"top": (2100.0, 900.0)})
            ctl.moving_state_reliable = False
            assert ctl.move_and_settle({"top": (2100.0, 900.0)}) == {"top": (2100.0, 900.0)}
        finally:
            ctl.close()
            tracker.link.close()


def test_a_clamping_channel_range_is_one_clear_error_and_keeps_the_rows(plant, rig_dir,
                                                                       capsys) -> None:
    # Factory Min/Max 992-2000 us; the 4th planned row commands 950.5 us on top's elbow.
    with device(plant, channel_range=(992.0, 2000.0)) as dev:
        code = main([*_collect_argv(rig_dir, dev.servo_port, dev.tracker_port, "--grid", "2",
                                    "--timeout", "1"), "--channels", *CHANNEL_ARGS])
        poses = list(dev.poses)
    err = capsys.readouterr().err
    assert code == 2
    line = [ln for ln in err.splitlines() if "error" in ln]
    assert len(line) == 1, err
    assert ("channel 1 (arm 'top' joint 2) was commanded 950.5 us but stays at 992 us"
            in line[0])
    assert "Maestro Control Center" in line[0] and "3 rows are safe" in line[0]
    assert keys(rig_dir) == planned(rig_dir, 2)[:3]
    assert all(u >= 992.0 for p in poses for pair in p.commands.values() for u in pair)


@pytest.mark.parametrize("on_error", ["home", "off"])
def test_a_row_measured_while_the_servos_went_home_is_measured_again(plant, rig_dir,
                                                                    on_error) -> None:
    hit = []

    def error_during_third_row(n: int) -> None:
        if n == 2:
            dev.inject_error()  # line noise: the Maestro sends its outputs home (or off)
            hit.append(dev.end_point)

    logs: list[str] = []
    with device(plant, seed=9, on_error=on_error) as dev:
        ctl, tracker = open_pair(dev)
        watch = Watching(tracker, dev, error_during_third_row)
        try:
            res = collect(rig_dir, ctl, watch, grid=2, plan=("train",), settle_s=0,
                          log=logs.append)
        finally:
            ctl.close()
            tracker.link.close()
    assert res.complete and res.recorded == 8
    assert keys(rig_dir) == planned(rig_dir, 2, sets=("train",))
    assert any("no longer outputs the row's pulses after reporting serial signal error" in s
               and "measuring the row again" in s for s in logs), logs
    assert any("1 measurements were discarded" in n for n in res.notes)
    # The third measurement was of the arm at home or limp; the row holds the fourth, taken
    # after the targets were sent again, and it reads the true end point of its commands.
    assert len(watch.seen) == 9
    rows = load_rig(rig_dir, min_train_rows=0).measurements
    commands, true_d, measured = watch.seen[3]
    assert np.allclose(rows.commands["top"][2], commands["top"])
    assert np.allclose(rows.observed[2], true_d, atol=2e-3)
    if on_error == "home":
        assert watch.seen[2][0]["top"] == (1500.0, 1500.0)  # it read the arm at home
        assert not np.allclose(watch.seen[2][2], rows.observed[2], atol=1.0)
    # measured again after the servos went home or limp: its approach sides are unknown
    assert [(r["top_d1"], r["top_d2"]) for r in _rows(rig_dir)][2] == ("0", "0")


def test_a_controller_that_keeps_dropping_its_targets_records_nothing_wrong(plant,
                                                                            rig_dir) -> None:
    def always(n: int) -> None:
        if n >= 2:
            dev.inject_error()

    with device(plant, on_error="off") as dev:
        ctl, tracker = open_pair(dev)
        try:
            with pytest.raises(HardwareError, match=r"\[3/20\].*no longer outputs.*3 times in "
                                                    r"a row; the row was not recorded.*2 rows "
                                                    r"are safe"):
                collect(rig_dir, ctl, Watching(tracker, dev, always), grid=2, settle_s=0,
                        log=lambda s: None)
        finally:
            ctl.close()
            tracker.link.close()
    assert keys(rig_dir) == planned(rig_dir, 2)[:2]


def test_an_error_at_any_moment_leaves_only_true_rows(plant, rig_dir) -> None:
    """The fault from sim-device's --error-after: wherever it lands (a settle, a measurement,
    a check), the run completes and every row reads its own commands' end point."""
    with device(plant, seed=2, on_error="off", faults=Faults(error_after=60)) as dev:
        ctl, tracker = open_pair(dev)
        watch = Watching(tracker, dev)
        try:
            res = collect(rig_dir, ctl, watch, grid=2, plan=("train",), settle_s=0,
                          log=lambda s: None)
        finally:
            ctl.close()
            tracker.link.close()
        assert dev.errors_raised == 1
    assert res.complete and keys(rig_dir) == planned(rig_dir, 2, sets=("train",))
    rows = load_rig(rig_dir, min_train_rows=0).measurements
    true = {(a, tuple(u)): d for c, d, _ in watch.seen for a, u in c.items()}
    for i, (arm, d) in enumerate(zip(rows.config, rows.observed, strict=True)):
        assert np.allclose(d, true[(arm, tuple(rows.commands[arm][i]))], atol=2e-3)


def test_tracker_outliers_are_rejected_and_reported(plant, rig_dir) -> None:
    with device(plant, seed=6, faults=Faults(outlier_rate=0.15)) as dev:
        ctl, tracker = open_pair(dev)
        tracker.samples = 9
        try:
            res = collect(rig_dir, ctl, tracker, grid=2, plan=("train",), settle_s=0,
                          log=lambda s: None)
        finally:
            ctl.close()
            tracker.link.close()
        poses = list(dev.poses)
        assert dev.outliers_sent > 0
    # 72 readings at 15 %: outliers are certain (P(none) = 0.85**72 < 1e-5); every one is
    # 5-50 mm off, far beyond 3.5 robust sd (floor 0.05 mm), so all that were read go.
    assert tracker.readings == 72 and tracker.outliers > 0
    assert any(f"tracker: {tracker.outliers} of 72 readings were rejected" in n
               for n in res.notes), res.notes
    # Tracker noise 0: once the outliers are gone every row reads its pose's true end point.
    obs = load_rig(rig_dir, min_train_rows=0).measurements.observed
    assert np.allclose(obs, [p.end_point for p in poses], atol=1e-3)


# ------------------------------------------------------------------------------ models, baud


@pytest.mark.parametrize(("model", "channels", "message"), [
    ("micro", ["top=0,1", "bottom=5,6"], "channel 6 of arm 'bottom' does not exist (a Micro "
                                         "Maestro 6 has channels 0..5)"),
    ("mini12", ["top=0,1", "bottom=11,12"], "channel 12 of arm 'bottom' does not exist (a Mini "
                                            "Maestro 12 has channels 0..11)"),
    ("mini18", ["top=17,18", "bottom=2,3"], "channel 18 of arm 'top'"),
])
def test_channels_beyond_the_maestro_model_are_refused_before_a_byte(plant, rig_dir, capsys,
                                                                     model, channels,
                                                                     message) -> None:
    with device(plant) as dev:
        code = main([*_collect_argv(rig_dir, dev.servo_port, dev.tracker_port),
                     "--maestro-model", model, "--channels", *channels])
        time.sleep(0.05)
        assert dev.received == b""
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and message in err, err
    assert not (rig_dir / "measurements.csv").exists()


def test_maestro_model_accepts_its_channels(plant, rig_dir, capsys) -> None:
    with device(plant, channels={"top": (4, 5), "bottom": (2, 3)}) as dev:
        code = main([*_collect_argv(rig_dir, dev.servo_port, dev.tracker_port, "--grid", "2",
                                    "--plan", "train"),
                     "--maestro-model", "micro", "--channels", "top=4,5", "bottom=2,3"])
    assert code == 0
    assert "connected: Micro Maestro 6 on" in capsys.readouterr().err
    assert keys(rig_dir) == planned(rig_dir, 2, sets=("train",))


@pytest.mark.parametrize(("wire", "auto_baud", "works"), [
    ("compact", False, False), ("compact", True, True), ("pololu", False, True)])
def test_uart_detect_baud_rate_mode(plant, rig_dir, wire, auto_baud, works) -> None:
    with device(plant, serial_mode="uart-detect") as dev:
        if works:
            res = run(dev, rig_dir, grid=2, plan=("train",), maestro_protocol=wire,
                      auto_baud=auto_baud, timeout_s=0.3)
            assert res.recorded == 8
            # The baud rate indication byte comes first: alone, or as a Pololu command's start.
            first = {"compact": b"\xaa\xa1", "pololu": b"\xaa\x0c\x21"}[wire]
            assert dev.received.startswith(first)
            assert not any("protocol error" in s for s in res.logs + res.notes)
        else:
            with pytest.raises(HardwareError, match="UART, detect baud rate.*--auto-baud"):
                run(dev, rig_dir, grid=2, plan=("train",), maestro_protocol=wire,
                    timeout_s=0.2, retries=2)
            assert not (rig_dir / "measurements.csv").exists()


def test_auto_baud_on_a_maestro_not_detecting_is_harmless(plant, rig_dir) -> None:
    """USB Dual Port: the lone 0xAA is a Pololu command cut short, a protocol error of ours."""
    with device(plant) as dev:
        res = run(dev, rig_dir, grid=2, plan=("train",), auto_baud=True)
        assert dev.received.startswith(b"\xaa\xa1")
    assert res.recorded == 8
    assert not any("protocol error" in s for s in res.logs + res.notes), (res.logs, res.notes)


def test_sim_device_command_line_quirk_options(sim_rig, capsys) -> None:
    assert main(["sim-device", str(sim_rig), "--protocol", "maestro", "--channel-range",
                 "2000,1000"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--channel-range: need 0 < MIN < MAX" in err
    from bayesrob.hardware.simdevice import parse_channel_range

    assert parse_channel_range("factory") == (992.0, 2000.0)
    assert parse_channel_range("500,2500") == (500.0, 2500.0)


def test_sim_device_command_serves_the_maestro_quirks(sim_rig) -> None:
    proc = subprocess.Popen([sys.executable, "-m", "bayesrob", "sim-device", str(sim_rig),
                             "--protocol", "maestro", "--serial-mode", "uart-detect",
                             "--channel-range", "factory", "--moving-state-bug",
                             "--on-error", "off", "--error-after", "9"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        servo_path = proc.stdout.readline().split(": ", 1)[1].strip()
        proc.stdout.readline()
        with serial.Serial(servo_path, timeout=2) as s:
            s.timeout = 0.3
            s.write(b"\x90\x00")  # before the baud rate byte: not understood, no answer
            assert s.read(2) == b""
            s.timeout = 2
            s.write(b"\xaa" + bytes([0xA1]))  # 1: baud byte, then Get Errors
            assert s.read(2) == b"\x00\x00"
            s.write(bytes([0x87, 0, 4, 0]))  # 2: Set Speed channel 0: 4 = 100 us/s
            s.write(bytes([0x84, 0, 0x10, 0x4E]))  # 3: Set Target 2500 us (10000 qus)
            s.write(bytes([0x93]))  # 4: Get Moving State: the bug answers 0 ...
            assert s.read(1) == b"\x00"
            s.write(bytes([0x90, 0]))  # 5: ... though the output is far from its target
            q = int.from_bytes(s.read(2), "little")
            assert 1500 * 4 <= q < 1600 * 4
            s.write(bytes([0x84, 1, 0x10, 0x4E]))  # 6: channel 1 (no speed limit) to 2500 us
            s.write(bytes([0x90, 1]))  # 7: clamped to the factory Max
            assert int.from_bytes(s.read(2), "little") == 2000 * 4
            s.write(bytes([0xA1]))  # 8
            assert s.read(2) == b"\x00\x00"
            s.write(bytes([0xA1]))  # 9: the injected error comes after this command
            assert s.read(2) == b"\x00\x00"
            s.write(bytes([0xA1, 0x90, 1]))  # serial signal error; outputs switched off
            assert s.read(4) == b"\x01\x00\x00\x00"
    finally:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err


def test_collect_measures_a_plan_in_its_order_and_resumes_it(plant, sim_rig, rig_dir) -> None:
    """``collect --plan poses.csv``: the planned rows (from ``bayesrob plan``), arm by arm (the
    tracker moves once per arm) and each arm's in the file's order, no grid and no linked
    rows; a second run with --resume finds them all recorded."""
    poses = rig_dir.parent / "poses.csv"
    assert main(["plan", str(sim_rig), "--n", "6", "--out", str(poses), "--samples",
                 "300"]) == 0
    with poses.open(newline="") as fh:
        planned = list(csv.DictReader(fh))
    with device(plant, seed=4) as dev:
        res = run(dev, rig_dir, poses=poses)
    assert res.complete and (res.recorded, res.total) == (6, 6)
    with (rig_dir / "measurements.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    planned = [p for arm in ("top", "bottom") for p in planned if p["config"] == arm]
    assert [r["config"] for r in rows] == [p["config"] for p in planned]
    for r, p in zip(rows, planned, strict=True):
        arm = p["config"]
        for k in (1, 2):  # quantised to the controller's resolution (0.25 us)
            assert abs(float(r[f"{arm}_u{k}"]) - float(p[f"{arm}_u{k}"])) <= 0.125
    with device(plant, seed=4) as dev:
        again = run(dev, rig_dir, poses=poses, resume=True)
    assert (again.recorded, again.skipped) == (0, 6)


# ------------------------------------------------------------------------------ approach sides


def _rows(rig_dir: Path) -> list[dict[str, str]]:
    with (rig_dir / "measurements.csv").open(newline="") as fh:
        return list(csv.DictReader(fh))


def _expected_sides(rows: list[dict[str, str]]) -> list[dict[str, str]]:
    """Each row's <arm>_dK as the sign of the arm's move from its command in the row before
    that commanded it (0 for its first), empty for arms the row leaves out."""
    last: dict[str, list[float]] = {}
    out = []
    for r in rows:
        want = {f"{a}_d{k}": "" for a in CHANNELS for k in (1, 2)}
        for a in r["config"].split("+"):
            u = [float(r[f"{a}_u{k}"]) for k in (1, 2)]
            for k in (1, 2):
                want[f"{a}_d{k}"] = str(int(np.sign(u[k - 1] - last[a][k - 1]))
                                        if a in last else 0)
            last[a] = u
        out.append(want)
    return out


def test_collect_records_each_joints_approach_side(plant, rig_dir) -> None:
    with device(plant, seed=2) as dev:
        res = run(dev, rig_dir, grid=2)
    assert res.complete
    rows = _rows(rig_dir)
    got = [{c: r[c] for c in want} for r, want in zip(rows, _expected_sides(rows), strict=True)]
    assert got == _expected_sides(rows)
    # every side occurs: the grid's moves go both ways, and each arm starts from nothing
    values = {v for g in got for v in g.values()}
    assert values == {"", "0", "1", "-1"}
    assert got[0] == {"top_d1": "0", "top_d2": "0", "bottom_d1": "", "bottom_d2": ""}
    extra = load_rig(rig_dir, min_train_rows=0).measurements.extra
    assert extra["bottom_d1"] == [r["bottom_d1"] for r in rows]


def test_resumed_collect_takes_sides_from_the_last_recorded_row(plant, rig_dir) -> None:
    with device(plant, seed=5) as dev:
        run(dev, rig_dir, grid=2, plan=("train",))
        res = run(dev, rig_dir, grid=2, plan=("train", "validation"), resume=True)
    assert (res.skipped, res.recorded) == (8, 8)
    rows = _rows(rig_dir)
    assert [{c: r[c] for c in want} for r, want in zip(rows, _expected_sides(rows),
                                                        strict=True)] == _expected_sides(rows)
    # the first resumed row (top's first validation row) moved from top's last train row,
    # not from nothing
    assert (rows[8]["config"], rows[8]["set"]) == ("top", "validation")
    assert {rows[8]["top_d1"], rows[8]["top_d2"]} != {"0"}


def test_a_file_without_approach_columns_resumes_in_its_own_form(plant, rig_dir) -> None:
    from bayesrob.data.rig import measurement_header

    old = ",".join(measurement_header(CHANNELS)) + "\n"
    (rig_dir / "measurements.csv").write_text(old)
    with device(plant) as dev:
        res = run(dev, rig_dir, grid=2, plan=("train",), resume=True)
    assert res.complete and res.recorded == 8
    assert (rig_dir / "measurements.csv").read_text().startswith(old)
    assert all("top_d1" not in r for r in _rows(rig_dir))
