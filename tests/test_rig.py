"""The rig format: what loads, and a one-line RigError for every way a rig can be wrong.

Each bad case checks that the message is one line, names the file, names the row (line) or
key (column), and says what is wrong.
"""

from __future__ import annotations

import csv
import json
import math
import tomllib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from bayesrob.data.rig import MEASUREMENTS_FILE, RIG_FILE, SETS, RigError, load_rig

# ----------------------------------------------------------------------------- helpers


def read_csv(path: Path) -> tuple[list[str], list[list[str]]]:
    with path.open(newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    return rows[0], rows[1:]


def write_csv(path: Path, header: list[str], rows: list[list[str]], newline: str = "\n") -> None:
    with path.open("w", newline="", encoding="utf-8") as fh:
        csv.writer(fh, lineterminator=newline).writerows([header, *rows])


def edit_row(rig: Path, config: str, set_name: str, /, **cells: str) -> int:
    """Set cells of the third row of ``config`` in ``set_name``; returns its line number."""
    path = rig / MEASUREMENTS_FILE
    header, rows = read_csv(path)
    matching = [i for i, r in enumerate(rows)
                if r[header.index("config")] == config and r[header.index("set")] == set_name]
    i = matching[2]
    for column, value in cells.items():
        rows[i][header.index(column)] = value
    write_csv(path, header, rows)
    return i + 2  # header is line 1, one record per line


def read_toml(rig: Path) -> dict:
    return tomllib.loads((rig / RIG_FILE).read_text(encoding="utf-8"))


def _toml_value(v: object) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, float) and not math.isfinite(v):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")
    return repr(v)


def write_toml(rig: Path, doc: dict) -> None:
    """A plain TOML writer of our own, so the cases do not lean on the project's writer."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in doc.items() if k != "arms"]
    for name, arm in doc.get("arms", {}).items():
        lines += ["", f"[arms.{json.dumps(name)}]"]
        if isinstance(arm, dict):
            lines += [f"{k} = {_toml_value(v)}" for k, v in arm.items()]
    (rig / RIG_FILE).write_text("\n".join(lines) + "\n", encoding="utf-8")


def rig_error(rig: Path, **kwargs) -> str:
    """The RigError message of loading ``rig``, checked to be one non-empty line."""
    with pytest.raises(RigError) as info:
        load_rig(rig, **kwargs)
    msg = str(info.value)
    assert msg.strip(), "empty message"
    assert "\n" not in msg and "\r" not in msg, f"message is not one line: {msg!r}"
    return msg


def assert_mentions(msg: str, *parts: str) -> None:
    for part in parts:
        assert part in msg, f"{part!r} not in message {msg!r}"


def same_measurements(a, b) -> None:
    """Two loaded rigs hold the same rows (line numbers aside)."""
    ma, mb = a.measurements, b.measurements
    assert ma.config.tolist() == mb.config.tolist()
    assert ma.set.tolist() == mb.set.tolist()
    np.testing.assert_array_equal(ma.target, mb.target)
    np.testing.assert_array_equal(ma.observed, mb.observed)
    assert ma.commands.keys() == mb.commands.keys()
    for arm in ma.commands:
        np.testing.assert_array_equal(ma.commands[arm], mb.commands[arm])
    assert a.arms == b.arms


# ----------------------------------------------------------------------------- valid rigs


def test_clean_rig_loads(clean_rig_dir):
    rig = load_rig(clean_rig_dir)
    meas = rig.measurements
    assert list(rig.arms) == ["top", "bottom"]
    assert rig.configs == ["top", "bottom", "top+bottom"]
    assert rig.linked_configs == ["top+bottom"]
    assert len(meas) == 80
    for config in ("top", "bottom"):
        for s in ("train", "validation"):
            assert meas.mask(config, s).sum() == 16
    assert meas.mask("top+bottom", "test").sum() == 16
    assert meas.line.tolist() == list(range(2, 82))
    single = meas.config != "top+bottom"
    assert np.isnan(meas.target[single]).all() and np.isfinite(meas.target[~single]).all()
    assert np.isnan(meas.commands["bottom"][meas.config == "top"]).all()
    assert np.isfinite(meas.observed).all()
    u, d = rig.rows("top", "train")
    assert u.shape == d.shape == (16, 2) and np.isfinite(u).all()
    rows = rig.config_rows("top+bottom", "test")
    assert set(rows["commands"]) == {"top", "bottom"}
    assert rows["target"].shape == rows["observed"].shape == (16, 2)
    assert rig.gravity == (0.0, -1.0)
    assert rig.path == clean_rig_dir


def test_columns_reordered_and_extra_columns_kept(clean_rig_dir, rig_copy):
    header, rows = read_csv(rig_copy / MEASUREMENTS_FILE)
    order = list(reversed(range(len(header))))
    new_header = ["note"] + [header[i] for i in order] + ["operator"]
    new_rows = [[f"row {k}"] + [r[i] for i in order] + ["kim"] for k, r in enumerate(rows)]
    write_csv(rig_copy / MEASUREMENTS_FILE, new_header, new_rows)
    rig = load_rig(rig_copy)
    same_measurements(rig, load_rig(clean_rig_dir))
    assert rig.measurements.extra == {"note": [f"row {k}" for k in range(len(rows))],
                                      "operator": ["kim"] * len(rows)}


def test_crlf_line_endings(clean_rig_dir, rig_copy):
    header, rows = read_csv(rig_copy / MEASUREMENTS_FILE)
    write_csv(rig_copy / MEASUREMENTS_FILE, header, rows, newline="\r\n")
    toml = rig_copy / RIG_FILE
    toml.write_bytes(toml.read_bytes().replace(b"\n", b"\r\n"))
    assert b"\r\n" in (rig_copy / MEASUREMENTS_FILE).read_bytes()
    rig = load_rig(rig_copy)
    same_measurements(rig, load_rig(clean_rig_dir))
    assert rig.measurements.line.tolist() == list(range(2, 82))


def test_blank_lines_are_skipped_and_lines_still_counted(clean_rig_dir, rig_copy):
    path = rig_copy / MEASUREMENTS_FILE
    lines = path.read_text(encoding="utf-8").splitlines()
    # a blank line after row 3, a line of empty fields, and blank lines at the end
    lines = lines[:4] + [""] + lines[4:10] + [",,,,,,,,,"] + lines[10:] + ["", ""]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    rig = load_rig(rig_copy)
    same_measurements(rig, load_rig(clean_rig_dir))
    assert rig.measurements.line[:4].tolist() == [2, 3, 4, 6]
    assert rig.measurements.line[-1] == 83


def test_values_with_spaces(clean_rig_dir, rig_copy):
    header, rows = read_csv(rig_copy / MEASUREMENTS_FILE)
    header = [f" {h} " for h in header]
    rows = [[f"  {c} " if c else " " for c in r] for r in rows]
    for r in rows:
        r[0] = r[0].replace("+", " + ")
    write_csv(rig_copy / MEASUREMENTS_FILE, header, rows)
    rig = load_rig(rig_copy)
    same_measurements(rig, load_rig(clean_rig_dir))
    assert rig.configs == ["top", "bottom", "top+bottom"]
    assert rig.config_rows("top+bottom", "test")["observed"].shape == (16, 2)


def test_integers_floats_and_exponents_are_numbers(rig_copy):
    header, rows = read_csv(rig_copy / MEASUREMENTS_FILE)
    col = {h: i for i, h in enumerate(header)}
    rows[0][col["top_u1"]], rows[0][col["top_u2"]] = "1500", "1.5e3"
    rows[0][col["x"]], rows[0][col["y"]] = "100", "+200.50"
    rows[1][col["top_u1"]], rows[1][col["x"]] = "1500.000", "-1.25E+01"
    write_csv(rig_copy / MEASUREMENTS_FILE, header, rows)
    meas = load_rig(rig_copy).measurements
    assert meas.commands["top"][0].tolist() == [1500.0, 1500.0]
    assert meas.observed[0].tolist() == [100.0, 200.5]
    assert meas.commands["top"][1, 0] == 1500.0 and meas.observed[1, 0] == -12.5
    assert meas.commands["top"].dtype == np.float64


def test_utf8_byte_order_mark_is_accepted(clean_rig_dir, rig_copy):
    # Spreadsheets and some editors start UTF-8 files with a byte order mark.
    for name in (MEASUREMENTS_FILE, RIG_FILE):
        path = rig_copy / name
        path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    same_measurements(load_rig(rig_copy), load_rig(clean_rig_dir))


def test_optional_toml_keys_take_defaults(rig_copy):
    doc = read_toml(rig_copy)
    for key in ("name", "gravity", "workspace"):
        doc.pop(key)
    for arm in doc["arms"].values():
        arm.pop("elbow")
        arm.pop("pulse_limits")
    write_toml(rig_copy, doc)
    rig = load_rig(rig_copy)
    assert rig.name == rig_copy.name
    assert rig.gravity == (0.0, -1.0)
    assert rig.workspace is None
    for arm in rig.arms.values():
        assert arm.elbow == 1
        assert arm.pulse_limits == ((500.0, 2500.0), (500.0, 2500.0))


def test_gravity_is_normalised_and_integers_accepted_in_toml(rig_copy):
    doc = read_toml(rig_copy)
    doc["gravity"] = [3, -4]
    doc["arms"]["top"]["base"] = [20, 440]
    doc["arms"]["top"]["elbow"] = -1
    write_toml(rig_copy, doc)
    rig = load_rig(rig_copy)
    assert rig.gravity == pytest.approx((0.6, -0.8))
    assert rig.arms["top"].base == (20.0, 440.0)
    assert isinstance(rig.arms["top"].base[0], float)
    assert rig.arms["top"].elbow == -1


def test_handmade_three_arm_rig(handmade_rig_dir):
    """A rig no simulator wrote: other arm names, three arms, own column order."""
    rig = load_rig(handmade_rig_dir)
    meas = rig.measurements
    assert rig.name == "bench"
    assert list(rig.arms) == ["left", "right", "middle"]
    assert rig.configs == ["left", "right", "middle", "left+right", "left+middle+right"]
    assert rig.arms["left"].pulse_limits == ((1000.0, 2000.0), (900.0, 2100.0))
    assert rig.arms["left"].base == (0.0, 0.0)
    assert rig.arms["right"].elbow == -1
    assert rig.workspace is None
    assert len(meas) == 3 * 12 + 5
    assert meas.mask("left", "train").sum() == 9 and meas.mask("left", "validation").sum() == 3
    rows = rig.config_rows("left+middle+right", "test")
    assert set(rows["commands"]) == {"left", "middle", "right"}
    np.testing.assert_array_equal(rows["target"], [[150.0, 120.0], [160.0, 140.0]])
    assert np.isnan(meas.commands["middle"][meas.mask("left+right")]).all()
    assert np.isnan(meas.target[meas.mask("right")]).all()
    assert meas.commands["left"][meas.mask("left", "validation")][2].tolist() == [1450.5, 1600.25]
    assert set(meas.extra) == {"timestamp", "operator"}
    assert meas.extra["operator"] == ["kim"] * len(meas)


def test_quoted_field_spanning_lines(handmade_rig_dir):
    """Records are not lines: a note with a line break must not shift later line numbers."""
    path = handmade_rig_dir / MEASUREMENTS_FILE
    header, rows = read_csv(path)
    op = header.index("operator")
    rows[0][op] = "kim\nsecond shift, \"quoted\""
    write_csv(path, header, rows)
    rig = load_rig(handmade_rig_dir)
    assert rig.measurements.extra["operator"][0] == "kim\nsecond shift, \"quoted\""
    assert rig.measurements.line[:3].tolist() == [2, 4, 5]
    rows[4][header.index("x")] = "oops"
    write_csv(path, header, rows)
    assert_mentions(rig_error(handmade_rig_dir), "line 7:", "'x'", "not a number")


def test_min_train_rows_zero_accepts_a_rig_being_collected(rig_copy):
    header, rows = read_csv(rig_copy / MEASUREMENTS_FILE)
    write_csv(rig_copy / MEASUREMENTS_FILE, header, rows[:3])
    assert len(load_rig(rig_copy, min_train_rows=0).measurements) == 3
    rig_error(rig_copy)


# ----------------------------------------------------------------------------- bad measurements.csv
# Each case breaks a copy of the clean rig and returns what the message must mention
# besides the path of measurements.csv.

CSV_CASES: dict[str, Callable[[Path], list[str]]] = {}


def csv_case(fn: Callable[[Path], list[str]]) -> Callable[[Path], list[str]]:
    CSV_CASES[fn.__name__] = fn
    return fn


@csv_case
def missing_file(rig):
    (rig / MEASUREMENTS_FILE).unlink()
    return ["not found"]


@csv_case
def empty_file(rig):
    (rig / MEASUREMENTS_FILE).write_bytes(b"")
    return ["empty", "header"]


@csv_case
def header_only(rig):
    header, _ = read_csv(rig / MEASUREMENTS_FILE)
    write_csv(rig / MEASUREMENTS_FILE, header, [])
    return ["no measurement rows"]


def _drop_column(rig: Path, column: str) -> None:
    header, rows = read_csv(rig / MEASUREMENTS_FILE)
    i = header.index(column)
    write_csv(rig / MEASUREMENTS_FILE, header[:i] + header[i + 1:],
              [r[:i] + r[i + 1:] for r in rows])


@csv_case
def missing_column_x(rig):
    _drop_column(rig, "x")
    return ["missing column 'x'"]


@csv_case
def missing_column_of_an_arm(rig):
    _drop_column(rig, "bottom_u2")
    return ["missing column 'bottom_u2'"]


@csv_case
def missing_column_set(rig):
    _drop_column(rig, "set")
    return ["missing column 'set'"]


@csv_case
def header_misspelt(rig):
    path = rig / MEASUREMENTS_FILE
    path.write_text(path.read_text(encoding="utf-8").replace("target_y", "targety", 1),
                    encoding="utf-8")
    return ["missing column 'target_y'"]


@csv_case
def duplicate_column(rig):
    header, rows = read_csv(rig / MEASUREMENTS_FILE)
    write_csv(rig / MEASUREMENTS_FILE, header + ["x"], [r + [r[-2]] for r in rows])
    return ["duplicate column 'x'"]


@csv_case
def unknown_arm_in_config(rig):
    line = edit_row(rig, "top", "train", config="middle")
    return [f"line {line}:", "unknown arm 'middle'", "top, bottom"]


@csv_case
def unknown_arm_in_linked_config(rig):
    line = edit_row(rig, "top+bottom", "test", config="top+botom")
    return [f"line {line}:", "unknown arm 'botom'"]


@csv_case
def config_case_differs(rig):
    line = edit_row(rig, "top", "validation", config="Top")
    return [f"line {line}:", "unknown arm 'Top'"]


@csv_case
def config_names_same_arm_twice(rig):
    line = edit_row(rig, "top+bottom", "test", config="top+top")
    return [f"line {line}:", "'top+top'", "same arm twice"]


@csv_case
def config_empty(rig):
    line = edit_row(rig, "top", "train", config="")
    return [f"line {line}:", "'config'", "empty"]


@csv_case
def config_dangling_plus(rig):
    line = edit_row(rig, "top+bottom", "test", config="top+")
    return [f"line {line}:", "'config'", "malformed"]


@csv_case
def bad_set_name(rig):
    line = edit_row(rig, "bottom", "validation", set="valid")
    return [f"line {line}:", "'set'", "'valid'", "train, validation, test"]


@csv_case
def empty_set(rig):
    line = edit_row(rig, "bottom", "train", set="")
    return [f"line {line}:", "'set'", "''"]


@csv_case
def non_numeric_pulse(rig):
    line = edit_row(rig, "top", "train", top_u1="15OO")
    return [f"line {line}:", "'top_u1'", "not a number", "'15OO'"]


@csv_case
def decimal_comma(rig):
    line = edit_row(rig, "bottom", "train", y="12,5")  # quoted by the csv writer
    return [f"line {line}:", "'y'", "not a number", "'12,5'"]


@csv_case
def nan_observed(rig):
    line = edit_row(rig, "top", "validation", x="NaN")
    return [f"line {line}:", "'x'", "finite", "'NaN'"]


@csv_case
def nan_pulse(rig):
    line = edit_row(rig, "bottom", "train", bottom_u2="nan")
    return [f"line {line}:", "'bottom_u2'", "finite"]


@csv_case
def inf_observed(rig):
    line = edit_row(rig, "bottom", "validation", y="inf")
    return [f"line {line}:", "'y'", "finite"]


@csv_case
def minus_infinity_target(rig):
    line = edit_row(rig, "top+bottom", "test", target_x="-Infinity")
    return [f"line {line}:", "'target_x'", "finite"]


@csv_case
def overflowing_number(rig):
    line = edit_row(rig, "top", "train", y="1e999")
    return [f"line {line}:", "'y'", "finite"]


@csv_case
def empty_x(rig):
    line = edit_row(rig, "top", "train", x="")
    return [f"line {line}:", "'x'", "empty"]


@csv_case
def empty_y_of_linked_row(rig):
    line = edit_row(rig, "top+bottom", "test", y="  ")
    return [f"line {line}:", "'y'", "empty"]


@csv_case
def pulse_above_limits(rig):
    line = edit_row(rig, "top", "train", top_u1="2400.25")  # limits are [600, 2400]
    return [f"line {line}:", "'top_u1'", "2400.25", "pulse_limits", "[600, 2400]"]


@csv_case
def pulse_below_limits_in_linked_row(rig):
    line = edit_row(rig, "top+bottom", "test", bottom_u2="599.75")
    return [f"line {line}:", "'bottom_u2'", "599.75", "pulse_limits"]


@csv_case
def target_outside_reach(rig):
    line = edit_row(rig, "top+bottom", "test", target_x="900", target_y="900")
    return [f"line {line}:", "target (900, 900)", "outside", "reach"]


@csv_case
def target_outside_one_linked_arms_reach(rig):
    # about 380 mm below the bottom arm's base (within its reach), 840 mm from the top arm's
    line = edit_row(rig, "top+bottom", "test", target_x="20", target_y="-400")
    return [f"line {line}:", "target (20, -400)", "arm 'top'", "reach"]


@csv_case
def target_outside_reach_of_single_arm(rig):
    line = edit_row(rig, "bottom", "train", target_x="20", target_y="900")
    return [f"line {line}:", "arm 'bottom'", "reach"]


@csv_case
def only_one_target_coordinate(rig):
    line = edit_row(rig, "top+bottom", "test", target_y="")
    return [f"line {line}:", "target_x and target_y"]


@csv_case
def linked_row_without_target(rig):
    line = edit_row(rig, "top+bottom", "test", target_x="", target_y="")
    return [f"line {line}:", "'top+bottom'", "target_x"]


@csv_case
def linked_row_missing_one_arms_commands(rig):
    line = edit_row(rig, "top+bottom", "test", bottom_u1="", bottom_u2="")
    return [f"line {line}:", "linked row", "missing", "arm 'bottom'", "'bottom_u1'"]


@csv_case
def linked_row_missing_one_command(rig):
    line = edit_row(rig, "top+bottom", "test", top_u2="")
    return [f"line {line}:", "linked row", "missing", "arm 'top'", "'top_u2'"]


@csv_case
def single_arm_row_missing_its_command(rig):
    line = edit_row(rig, "bottom", "validation", bottom_u1="")
    return [f"line {line}:", "missing", "'bottom_u1'"]


@csv_case
def garbage_in_other_arms_column(rig):
    # bottom's columns on a top row are ignored, but text there hints at a mistyped config
    line = edit_row(rig, "top", "train", bottom_u1="top")
    return [f"line {line}:", "'bottom_u1'", "not a number"]


@csv_case
def too_many_fields(rig):
    path = rig / MEASUREMENTS_FILE
    lines = path.read_text(encoding="utf-8").splitlines()
    lines[9] += ",extra"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return ["line 10:", "expected 10 fields, found 11"]


@csv_case
def too_few_fields(rig):
    path = rig / MEASUREMENTS_FILE
    lines = path.read_text(encoding="utf-8").splitlines()
    lines[20] = lines[20].rsplit(",", 1)[0]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return ["line 21:", "expected 10 fields, found 9"]


@csv_case
def fewer_train_rows_than_parameters(rig):
    header, rows = read_csv(rig / MEASUREMENTS_FILE)
    top_train = [i for i, r in enumerate(rows) if r[0] == "top" and r[1] == "train"]
    drop = set(top_train[7:])
    write_csv(rig / MEASUREMENTS_FILE, header, [r for i, r in enumerate(rows) if i not in drop])
    return ["arm 'top'", "7 train rows", "8 parameters"]


@csv_case
def arm_without_train_rows(rig):
    header, rows = read_csv(rig / MEASUREMENTS_FILE)
    write_csv(rig / MEASUREMENTS_FILE, header,
              [r for r in rows if not (r[0] == "bottom" and r[1] == "train")])
    return ["arm 'bottom'", "0 train rows"]


@csv_case
def non_utf8_bytes(rig):
    path = rig / MEASUREMENTS_FILE
    lines = path.read_bytes().split(b"\n")
    lines[5] = lines[5].replace(b"train", b"tr\xe4in")  # Latin-1, not UTF-8
    path.write_bytes(b"\n".join(lines))
    return ["line 6:", "UTF-8"]


@csv_case
def utf16_file(rig):
    path = rig / MEASUREMENTS_FILE
    path.write_bytes(path.read_text(encoding="utf-8").encode("utf-16"))
    return ["UTF-8"]


@csv_case
def file_is_a_directory(rig):
    (rig / MEASUREMENTS_FILE).unlink()
    (rig / MEASUREMENTS_FILE).mkdir()
    return ["not found"]


@pytest.mark.parametrize("case", list(CSV_CASES))
def test_bad_measurements(rig_copy, case):
    parts = CSV_CASES[case](rig_copy)
    msg = rig_error(rig_copy)
    assert_mentions(msg, f"{rig_copy / MEASUREMENTS_FILE}:", *parts)


# ----------------------------------------------------------------------------- bad rig.toml
# Each case edits the parsed rig.toml of a copy of the clean rig (written back with our own
# writer) and returns what the message must mention besides the path of rig.toml.

TOML_CASES: dict[str, Callable[[dict], list[str]]] = {}


def toml_case(fn: Callable[[dict], list[str]]) -> Callable[[dict], list[str]]:
    TOML_CASES[fn.__name__] = fn
    return fn


@toml_case
def no_arms(doc):
    del doc["arms"]
    return ["missing key 'arms'"]


@toml_case
def arm_missing_gain(doc):
    del doc["arms"]["bottom"]["gain"]
    return ["[arms.bottom]", "missing key 'gain'"]


@toml_case
def arm_missing_base(doc):
    del doc["arms"]["top"]["base"]
    return ["[arms.top]", "missing key 'base'"]


@toml_case
def links_is_a_string(doc):
    doc["arms"]["top"]["links"] = "240, 220"
    return ["arms.top.links", "two numbers"]


@toml_case
def links_has_three_values(doc):
    doc["arms"]["top"]["links"] = [240.0, 220.0, 10.0]
    return ["arms.top.links", "two numbers"]


@toml_case
def base_holds_a_string(doc):
    doc["arms"]["bottom"]["base"] = [20.0, "-20"]
    return ["arms.bottom.base", "numbers"]


@toml_case
def base_holds_a_boolean(doc):
    doc["arms"]["bottom"]["base"] = [True, 1.0]
    return ["arms.bottom.base", "numbers"]


@toml_case
def nan_in_toml(doc):
    doc["arms"]["top"]["offset"] = [math.nan, 0.1]
    return ["arms.top.offset", "finite"]


@toml_case
def inf_in_toml(doc):
    doc["arms"]["bottom"]["links"] = [math.inf, 200.0]
    return ["arms.bottom.links", "finite"]


@toml_case
def negative_link(doc):
    doc["arms"]["bottom"]["links"] = [220.0, -200.0]
    return ["arms.bottom.links", "positive"]


@toml_case
def zero_gain(doc):
    doc["arms"]["top"]["gain"] = [0.0015, 0]
    return ["arms.top.gain", "non-zero"]


@toml_case
def elbow_two(doc):
    doc["arms"]["top"]["elbow"] = 2
    return ["arms.top.elbow", "+1 or -1", "2"]


@toml_case
def elbow_zero(doc):
    doc["arms"]["bottom"]["elbow"] = 0
    return ["arms.bottom.elbow", "+1 or -1"]


@toml_case
def elbow_boolean(doc):
    doc["arms"]["top"]["elbow"] = True
    return ["arms.top.elbow", "+1 or -1"]


@toml_case
def elbow_string(doc):
    doc["arms"]["top"]["elbow"] = "-1"
    return ["arms.top.elbow", "+1 or -1"]


@toml_case
def pulse_limits_reversed(doc):
    doc["arms"]["bottom"]["pulse_limits"] = [[600.0, 2400.0], [2400.0, 600.0]]
    return ["arms.bottom.pulse_limits[1]", "lo < hi"]


@toml_case
def pulse_limits_flat(doc):
    doc["arms"]["top"]["pulse_limits"] = [600.0, 2400.0]
    return ["arms.top.pulse_limits", "two numbers"]


@toml_case
def pulse_limits_single_pair(doc):
    doc["arms"]["top"]["pulse_limits"] = [[600.0, 2400.0]]
    return ["arms.top.pulse_limits", "[[lo, hi], [lo, hi]]"]


@toml_case
def gravity_zero(doc):
    doc["gravity"] = [0, 0.0]
    return ["gravity", "non-zero"]


@toml_case
def gravity_string(doc):
    doc["gravity"] = "down"
    return ["gravity", "two numbers"]


@toml_case
def workspace_flat(doc):
    doc["workspace"] = [80.0, 260.0, 100.0, 280.0]
    return ["workspace", "[[x0, x1], [y0, y1]]"]


@toml_case
def name_not_a_string(doc):
    doc["name"] = 5
    return ["name", "string"]


@toml_case
def arm_name_with_plus(doc):
    doc["arms"]["a+b"] = doc["arms"].pop("bottom")
    return ["'a+b'", "'+'"]


@toml_case
def arm_name_with_comma(doc):
    doc["arms"]["a,b"] = doc["arms"].pop("bottom")
    return ["'a,b'", "','"]


@toml_case
def arm_name_blank(doc):
    doc["arms"][" "] = doc["arms"].pop("bottom")
    return ["arm name", "empty"]


@toml_case
def arm_name_padded(doc):
    doc["arms"]["bottom "] = doc["arms"].pop("bottom")
    return ["'bottom '", "space"]


@toml_case
def duplicate_arm_names_by_case(doc):
    doc["arms"]["Top"] = dict(doc["arms"]["top"])
    return ["duplicate arm name", "'top'"]


@pytest.mark.parametrize("case", list(TOML_CASES))
def test_bad_rig_toml(rig_copy, case):
    doc = read_toml(rig_copy)
    parts = TOML_CASES[case](doc)
    write_toml(rig_copy, doc)
    msg = rig_error(rig_copy)
    assert_mentions(msg, f"{rig_copy / RIG_FILE}:", *parts)


# Cases that need the text itself: each returns the text of rig.toml to write.
TOML_TEXT_CASES = {
    "unclosed_array": (lambda t: t.replace("links = [240", "links = [240,,", 1),
                       ["invalid TOML", "line "]),
    "missing_equals": (lambda t: t + "\n[arms.extra]\nbase [1, 2]\n", ["invalid TOML", "line "]),
    "duplicate_key": (lambda t: t.replace("elbow = 1", "elbow = 1\nelbow = 1", 1),
                      ["invalid TOML", "line "]),
    "duplicate_arm_table": (
        lambda t: t + "\n[arms.top]\nbase = [1, 2]\nlinks = [1, 2]\ngain = [1, 2]\n"
                      "offset = [1, 2]\n",
        ["duplicate arm name 'top'", "line "]),
    "arm_not_a_table": (lambda t: "arms.left = 5\n" + t, ["[arms.left]", "table"]),
    "arms_array_of_tables": (
        lambda t: "[[arms]]\nname = \"top\"\nbase = [1, 2]\n", ["'arms'", "[arms.<name>]",
                                                               "got a list"]),
    "empty_arms_table": (lambda t: "name = \"bench\"\n[arms]\n", ["'arms'", "empty table"]),
    "empty_file": (lambda t: "", ["missing key 'arms'"]),
    "non_utf8_bytes": (None, ["line 1:", "UTF-8"]),
    "missing_file": (None, ["not found"]),
}


@pytest.mark.parametrize("case", list(TOML_TEXT_CASES))
def test_bad_rig_toml_text(rig_copy, case):
    edit, parts = TOML_TEXT_CASES[case]
    path = rig_copy / RIG_FILE
    if case == "missing_file":
        path.unlink()
    elif case == "non_utf8_bytes":
        path.write_bytes(b"name = \"B\xfchne\"\n" + path.read_bytes().split(b"\n", 1)[1])
    else:
        doc = read_toml(rig_copy)
        doc["arms"]["top"]["links"] = [240, 220]
        write_toml(rig_copy, doc)
        old = path.read_text(encoding="utf-8")
        new = edit(old)
        assert new != old or case == "empty_file"
        path.write_text(new, encoding="utf-8")
    msg = rig_error(rig_copy)
    assert_mentions(msg, f"{path}:", *parts)


def test_arm_in_toml_without_columns(rig_copy):
    doc = read_toml(rig_copy)
    doc["arms"]["middle"] = dict(doc["arms"]["top"])
    write_toml(rig_copy, doc)
    msg = rig_error(rig_copy)
    assert_mentions(msg, f"{rig_copy / MEASUREMENTS_FILE}:", "missing column 'middle_u1'")


def test_missing_rig_directory(tmp_path):
    msg = rig_error(tmp_path / "nowhere")
    assert_mentions(msg, str(tmp_path / "nowhere"), "not found")


def test_toml_errors_come_before_measurement_errors(rig_copy):
    (rig_copy / MEASUREMENTS_FILE).unlink()
    (rig_copy / RIG_FILE).write_text("name = \n", encoding="utf-8")
    assert_mentions(rig_error(rig_copy), str(rig_copy / RIG_FILE))


def test_handmade_rig_errors_name_its_own_arms(handmade_rig_dir):
    rig = handmade_rig_dir
    header, rows = read_csv(rig / MEASUREMENTS_FILE)
    col = {h: i for i, h in enumerate(header)}
    i = next(i for i, r in enumerate(rows) if r[col["config"]] == "left+middle+right")
    rows[i][col["middle_u2"]] = ""
    write_csv(rig / MEASUREMENTS_FILE, header, rows)
    assert_mentions(rig_error(rig), f"line {i + 2}:", "arm 'middle'", "'middle_u2'")
    rows[i][col["middle_u2"]] = "1500"
    rows[i][col["left_u2"]] = "2150"  # left's own limits are [900, 2100]
    write_csv(rig / MEASUREMENTS_FILE, header, rows)
    assert_mentions(rig_error(rig), f"line {i + 2}:", "'left_u2'", "[900, 2100]")


def test_every_set_name_is_accepted(rig_copy):
    header, rows = read_csv(rig_copy / MEASUREMENTS_FILE)
    for k, r in enumerate(rows):
        if r[0] == "top+bottom":
            r[1] = SETS[k % len(SETS)]
    write_csv(rig_copy / MEASUREMENTS_FILE, header, rows)
    sets = set(load_rig(rig_copy).measurements.set.tolist())
    assert sets == set(SETS)


def test_misspelled_arm_key_is_refused_not_defaulted(rig_copy):
    toml = rig_copy / "rig.toml"
    toml.write_text(toml.read_text().replace("pulse_limits", "pulse_limit", 1))
    with pytest.raises(RigError, match=r"rig\.toml.*unknown key 'pulse_limit'.*'pulse_limits'"):
        load_rig(rig_copy)


def test_unknown_arm_key_is_refused_and_meta_is_the_place_for_other_tools(rig_copy):
    toml = rig_copy / "rig.toml"
    text = toml.read_text()
    toml.write_text(text.replace("[arms.top]\n", "[arms.top]\nservo_model = \"HSR-5995TG\"\n"))
    with pytest.raises(RigError, match=r"rig\.toml: \[arms\.top\] has unknown key "
                                       r"'servo_model'.*'meta' table"):
        load_rig(rig_copy)
    toml.write_text(text.replace("[arms.top]\n",
                                 "[arms.top]\nmeta = { servo_model = \"HSR-5995TG\" }\n"))
    assert load_rig(rig_copy).arms["top"].links


@pytest.mark.parametrize("typo, meant", [("gravty", "gravity"), ("workspce", "workspace"),
                                         ("nme", "name")])
def test_top_level_typo_is_refused_with_a_suggestion(rig_copy, typo, meant):
    toml = rig_copy / "rig.toml"
    value = {"gravty": "[0.0, -1.0]", "workspce": "[[0, 1], [0, 1]]", "nme": '"x"'}[typo]
    toml.write_text(f"{typo} = {value}\n" + toml.read_text())
    with pytest.raises(RigError, match=rf"rig\.toml: rig\.toml has unknown key '{typo}'; did "
                                       rf"you mean '{meant}'\?"):
        load_rig(rig_copy)


# ----------------------------------------------------------------------------- approach sides


def _with_sides(rig: Path, values: list[str]) -> int:
    """Add top_d1, top_d2 to every row (empty in the other arm's); ``values[0]`` goes into the
    third top train row's top_d1. Returns that row's line."""
    path = rig / MEASUREMENTS_FILE
    header, rows = read_csv(path)
    write_csv(path, header + ["top_d1", "top_d2"],
              [r + (["1", "-1"] if r[0] == "top" else ["", ""]) for r in rows])
    return edit_row(rig, "top", "train", top_d1=values[0])


def test_approach_columns_load_and_are_kept(rig_copy):
    _with_sides(rig_copy, ["+1"])
    meas = load_rig(rig_copy).measurements
    top = meas.mask("top")
    assert set(meas.extra) == {"top_d1", "top_d2"}
    sides = np.array(meas.extra["top_d2"])
    assert (sides[top] == "-1").all() and (sides[~top] == "").all()
    assert meas.extra["top_d1"].count("+1") == 1


def test_approach_sides_reach_the_calibration_with_each_arms_rows(rig_copy):
    """The calibration's rows carry each arm's recorded sides (empty cells 0, unknown) under
    ``kin.APPROACH``, in the rows' order; an arm without such columns carries none."""
    from bayesrob import robot as kin

    _with_sides(rig_copy, ["-1"])
    rig = load_rig(rig_copy)
    top = rig.side_rows("top", "train")[kin.APPROACH]
    assert top.shape == (int(rig.measurements.mask("top", "train").sum()), 2)
    assert (top[:, 1] == -1).all() and sorted(set(top[:, 0])) == [-1.0, 1.0]
    assert rig.side_rows("bottom", "train") is None


@pytest.mark.parametrize("value", ["2", "x", "0.5"])
def test_bad_approach_sides_are_one_line_errors(rig_copy, value, capsys):
    from bayesrob.cli import main

    line = _with_sides(rig_copy, [value])
    assert_mentions(rig_error(rig_copy), f"{rig_copy / MEASUREMENTS_FILE}", f"line {line}:",
                    "'top_d1'")
    assert main(["calibrate", str(rig_copy)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and f"line {line}: column 'top_d1'" in err
