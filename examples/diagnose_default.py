"""Diagnose the embedded default rig: which physical effects is the paper's model missing?

    python examples/diagnose_default.py [REPORT_DIR]

The default rig was simulated with gravity sag and backlash switched on; the diagnosis
reads only its rig.toml and measurements.csv. It prints the terminal report, writes the
JSON document and the figures (residual quivers before/after per arm, the gap per step)
into REPORT_DIR (default: ./diagnosis-default) and returns the Diagnosis for further use.
The same as ``bayesrob diagnose --json REPORT_DIR/diagnosis.json --report REPORT_DIR``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import bayesrob  # noqa: F401  (64-bit JAX)
from bayesrob.data.rig import default_rig_dir, load_rig
from bayesrob.diagnose.refits import Diagnosis, diagnose
from bayesrob.report.outputs import write_diagnosis_report
from bayesrob.report.tables import format_diagnosis


def main(report_dir: str | Path = "diagnosis-default") -> Diagnosis:
    rig = load_rig(default_rig_dir())
    diag = diagnose(rig, progress=sys.stderr.isatty())
    doc = diag.to_json()
    print(format_diagnosis(doc))
    out = Path(report_dir)
    for path in write_diagnosis_report(diag, out):
        print(f"wrote {path}")
    (out / "diagnosis.json").write_text(json.dumps(doc, indent=2) + "\n")
    print(f"wrote {out / 'diagnosis.json'}")
    return diag


if __name__ == "__main__":
    main(*sys.argv[1:2])
