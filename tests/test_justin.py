"""DLR's Agile Justin: the conversion of the authors' file into a rig, on a few rows written
here (the real data, read from ../shared/data/ and never shipped, is the validation studies'
justin_ladder and justin_coverage), and the one-line error when the data is absent."""

from __future__ import annotations

import numpy as np
import pytest
from bayesrob.validation.justin import RIG_TOML, convert, justin_data

from bayesrob.data.rig import load_rig


def _authors_file(path, n: int) -> np.ndarray:
    """n poses in the authors' layout (numpy-printed arrays, metres); returns the markers."""
    rng = np.random.default_rng(0)
    markers = rng.uniform(-0.5, 0.5, (n, 2, 3))
    lines = [",joints,markers"]
    for i in range(n):
        q = np.array2string(rng.uniform(-1, 1, 19), precision=12, max_line_width=10_000)
        m = np.array2string(markers[i], precision=12, max_line_width=10_000)
        lines.append(f'{i},"{q}","{m}"')
    path.write_text("\n".join(lines) + "\n")
    return markers


def test_convert_splits_the_poses_into_two_marker_rows_each(tmp_path):
    markers = _authors_file(tmp_path / "m.csv", 5)
    assert convert(tmp_path / "m.csv", tmp_path / "rig", split=3) == 5
    assert (tmp_path / "rig" / "rig.toml").read_text() == RIG_TOML.read_text()
    rig = load_rig(tmp_path / "rig")
    m = rig.measurements
    # file order kept: the first 3 poses train, the rest validation, one row per hand
    assert list(m.config) == ["right", "left"] * 5
    assert list(m.set) == ["train"] * 6 + ["validation"] * 4
    np.testing.assert_allclose(m.observed.reshape(5, 2, 3), markers * 1000.0, atol=1e-4)
    # each hand's rows carry the other arm's columns too: its weight bends the torso
    _, obs = rig.rows("left", "validation")
    assert obs.shape == (2, 3)
    assert rig.side_rows("left", "validation")


def test_convert_names_the_line_of_a_malformed_array(tmp_path):
    _authors_file(tmp_path / "m.csv", 2)
    text = (tmp_path / "m.csv").read_text()
    (tmp_path / "m.csv").write_text(text.replace('\n1,"[', '\n1,"[x ', 1))
    with pytest.raises(SystemExit, match=r"m\.csv: line 3: joints: not a numeric array"):
        convert(tmp_path / "m.csv", tmp_path / "rig")


def test_the_studies_name_the_missing_data_in_one_line(tmp_path):
    missing = tmp_path / "agile-justin" / "measurements.csv"
    with pytest.raises(FileNotFoundError) as err:
        justin_data(missing)
    assert str(missing) in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("script", ["convert.py", "ladder.py", "coverage.py"])
def test_the_examples_run_from_any_directory(script, tmp_path):
    """The README runs them from the checkout's root, the docs from elsewhere: each finds its
    neighbours and the checkout's bayesrob wherever it is started, and a missing source file
    is one line naming it, exit 2 (convert.py is then run on a small file to the end)."""
    import subprocess
    import sys
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "examples" / "agile_justin" / script
    missing = tmp_path / "no" / "measurements.csv"
    args = [str(missing), str(tmp_path / "rig")] if script == "convert.py" else [str(missing)]
    r = subprocess.run([sys.executable, str(path), *args], cwd=tmp_path, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.splitlines() == [f"{missing}: file not found"], \
        r.stderr
    if script == "convert.py":
        _authors_file(tmp_path / "m.csv", 4)
        r = subprocess.run([sys.executable, str(path), "m.csv", "rig"], cwd=tmp_path,
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        assert load_rig(tmp_path / "rig").measurements.observed.shape == (8, 3)
