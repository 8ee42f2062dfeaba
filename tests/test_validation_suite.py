"""The validation suite's runner: studies side by side on a Dask cluster give the report that
running them in order gives, in the order they were named."""

from __future__ import annotations

import io
import re
import sys
import time
import types

import pytest
from bayesrob.validation.study import FAIL, PASS, Study, Target, discover_studies, repository
from bayesrob.validation.suite import markdown, run_suite

FAKE = "bayesrob.validation._fake_studies"


@pytest.fixture
def fake_studies(monkeypatch: pytest.MonkeyPatch) -> list[Study]:
    """Three studies of a module the test makes: the first is slowest (so it ends last when
    they run side by side), the second raises, the third misses its target."""
    module = types.ModuleType(FAKE)

    def slow(seeds, quick, say):
        time.sleep(0.6)
        say("slow rig done")
        return {"value": 1.0}

    def broken(seeds, quick, say):
        raise RuntimeError("the rig would not settle")

    def missing(seeds, quick, say):
        return {"value": 5.0}

    module.slow, module.broken, module.missing = slow, broken, missing
    monkeypatch.setitem(sys.modules, FAKE, module)
    target = (Target("value", max=2.0, quick_max=2.0),)
    return [Study(name=f, title=f"study {f}", module="_fake_studies", function=f,
                  fixed="by this test", tuning_seeds=(1,), report_seeds=(2, 3),
                  quick_seeds=(2,), targets=target) for f in ("slow", "broken", "missing")]


def _run(studies: list[Study], client=None) -> tuple[dict, list[str], str]:
    stream = io.StringIO()
    seen: list[str] = []
    report = run_suite(studies, quick=True, stream=stream, client=client,
                       after_each=lambda r: seen.append(",".join(r["studies"])))
    return report, seen, stream.getvalue()


def test_studies_side_by_side_report_what_in_order_reports(fake_studies, capsys):
    from distributed import Client, LocalCluster

    in_order, seen_in_order, _ = _run(fake_studies)
    # threads, not processes: the test's module of studies exists in this process only
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                      dashboard_address=":0") as cluster, Client(cluster) as client:
        side, seen_side, lines = _run(fake_studies, client)
    assert list(side["studies"]) == ["slow", "broken", "missing"]  # the order named
    for name in ("slow", "broken", "missing"):
        a, b = in_order["studies"][name], side["studies"][name]
        assert {k: a[k] for k in ("figures", "checks", "status", "error", "seeds")} == \
            {k: b[k] for k in ("figures", "checks", "status", "error", "seeds")}
    assert side["studies"]["slow"]["checks"] == {"value": PASS}
    assert side["studies"]["broken"]["error"] == "RuntimeError: the rig would not settle"
    assert side["studies"]["missing"]["checks"] == {"value": FAIL}
    assert side["status"] == in_order["status"] == "fail"
    assert (in_order["workers"], side["workers"]) == (1, 2)
    assert seen_in_order == ["slow", "slow,broken", "slow,broken,missing"]
    # side by side the slow study ends last, and each partial report keeps the named order
    assert seen_side[-1] == "slow,broken,missing" and seen_side[0] != "slow"
    assert "validate: [1/3] slow: pass in" in lines
    assert "validate: [2/3] broken: fail in" in lines and "would not settle" in lines
    assert "2 studies at a time" in markdown(side)
    assert "studies at a time" not in markdown(in_order)


def test_ci_runs_a_study_of_every_study_module():
    """CI runs one study of each module on its quick seeds, not all of them: a module added
    without one of its studies in that list would never run before a full validation."""
    script = (repository() / ".ci" / "run").read_text()
    (listed,) = re.findall(r"ci_studies=\(([^)]*)\)", script)
    names = listed.split()
    ran = {s.module for s in discover_studies(names)}  # an unknown name raises StudyError
    assert ran == {s.module for s in discover_studies()}
    assert '"${ci_studies[@]}"' in script
