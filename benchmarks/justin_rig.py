"""The Agile Justin rig the chain benchmarks run on: converted from the authors' file when it
is at hand, else a simulated 6-joint arm stands in (the benchmarks' case names say which)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = ROOT.parent / "shared" / "data" / "agile-justin" / "measurements.csv"


def justin_or_simulated(data: Path, rig_dir: Path, truth: Any) -> bool:
    """Write the rig into ``rig_dir``: Justin's from ``data`` if it exists (True), else the
    simulator's arm with ``truth`` (a ``ChainTruth``; False)."""
    if data.is_file():
        sys.path.insert(0, str(ROOT / "examples" / "agile_justin"))
        from convert import convert

        convert(data, rig_dir)
        return True
    from bayesrob.chain_simulator import simulate_chain_rig

    simulate_chain_rig(rig_dir, truth)
    return False
