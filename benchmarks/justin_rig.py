"""The Agile Justin rig the chain benchmarks run on: converted from the authors' file when it
is at hand, else a simulated 6-joint arm stands in (the benchmarks' case names say which)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from bayesrob.validation.justin import DATA as DEFAULT_DATA
from bayesrob.validation.justin import convert

__all__ = ["DEFAULT_DATA", "justin_or_simulated"]


def justin_or_simulated(data: Path, rig_dir: Path, truth: Any) -> bool:
    """Write the rig into ``rig_dir``: Justin's from ``data`` if it exists (True), else the
    simulator's arm with ``truth`` (a ``Arm6Truth``; False)."""
    if data.is_file():
        convert(data, rig_dir)
        return True
    from bayesrob.sim.rigs import simulate_arm6_rig

    simulate_arm6_rig(rig_dir, truth)
    return False
