"""Results schema, statistics and metrics of the evaluation (no processes)."""

import json

import numpy as np
import pytest

from racecav.evaluation import results as R
from racecav.evaluation.metrics import box_corners, footprint_gap


def test_committed_schema_is_the_generated_one():
    # docs/results-schema.json is generated from the models; regenerate with
    # `python -m racecav.evaluation.results --write-schema` after changing them
    assert json.loads(R.SCHEMA_PATH.read_text()) == json.loads(json.dumps(R.json_schema()))


def _trial(i, success, **kw):
    base = dict(index=i, seed=i, success=success, collided=not success, contact_with="" if success else "car1",
                contact_time_s=None if success else 3.9, end_time_s=8.0 if success else 3.9, progress_m=9.0,
                min_gap_m=0.3 if success else 0.0, min_center_distance_m=0.7, steps=81, commands=81,
                latency_ms=R.Stats(n=2, median=0.5, p99=0.9, max=0.9), compute_ms=R.Stats(n=2, median=0.01),
                wall_s=0.2, latency_steps_ms=[0.4, 0.6], compute_steps_ms=[0.01, 0.01])
    return R.Trial(**{**base, **kw})


def _run(trials):
    return R.RunResult(created_utc="2026-01-01T00:00:00Z", git_commit="x", machine="m",
                       scenario=R.ScenarioInfo(name="s", ref="s", digest="d" * 64, duration_s=8.0),
                       controller=R.ControllerInfo(name="scripted", command=["racecav", "scripted"], service="scripted"),
                       mode="lockstep", base_seed=0, trials_requested=len(trials), complete=True, wall_s=1.0,
                       summary=R.summarize(trials), trials=trials)


def test_results_validate_and_bad_results_name_the_field():
    run = _run([_trial(0, True), _trial(1, False)])
    data = json.loads(run.model_dump_json())
    assert R.validate_run(data).summary.successes == 1
    data["trials"][1]["success"] = "maybe"
    with pytest.raises(ValueError, match=r"trials\.1\.success"):
        R.validate_run(data)
    data = json.loads(run.model_dump_json())
    data["schema_version"] = 2
    with pytest.raises(ValueError, match="schema_version"):
        R.validate_run(data)
    del data["schema_version"], data["summary"]
    with pytest.raises(ValueError, match="summary"):
        R.validate_run(data)


def test_summary_pools_steps_and_wilson_interval():
    trials = [_trial(i, i < 8) for i in range(10)]
    s = R.summarize(trials)
    assert (s.trials, s.successes, s.collisions) == (10, 8, 2)
    assert s.latency_ms.n == 20 and s.latency_ms.median == pytest.approx(0.5)
    lo, hi = s.ci95
    assert lo == pytest.approx(0.4902, abs=1e-4) and hi == pytest.approx(0.9433, abs=1e-4)  # 8/10, Wilson
    assert R.wilson(0, 10)[0] == pytest.approx(0.0) and R.wilson(10, 10)[1] == pytest.approx(1.0)
    assert R.wilson(0, 0) is None


def test_jsonl_resume_refuses_another_run_and_skips_a_torn_line(tmp_path):
    p = tmp_path / "r.jsonl"
    R.append_jsonl(p, "k1", _trial(0, True))
    R.append_jsonl(p, "k1", _trial(1, False))
    with open(p, "a") as f:
        f.write('{"run_key": "k1", "trial": {"ind')  # killed mid-write
    done = R.read_jsonl(p, "k1")
    assert sorted(done) == [0, 1] and done[1].contact_with == "car1"
    with pytest.raises(ValueError, match="belongs to run 'k1'"):
        R.read_jsonl(p, "k2")


def test_footprint_gap():
    a = box_corners([0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], 0.5, 0.3)
    b = box_corners([1.0, 0.4, 0.0, 0.2], [0, 0, 0.5, 0.0], [0, np.pi / 2, 0, 0.3], 0.5, 0.3)
    gap = footprint_gap(a, b)
    assert gap[0] == pytest.approx(0.5)   # 1 m apart along x, 0.25 + 0.25 half-lengths
    assert gap[1] == pytest.approx(0.0, abs=1e-12)   # rotated box touching the front edge
    assert gap[2] == pytest.approx(0.2)   # side by side: 0.5 - 0.15 - 0.15
    assert gap[3] == 0.0                  # overlapping


def test_registry_controllers_are_commands_of_the_cli():
    import importlib.util

    from racecav.cli import COMMANDS
    from racecav.common.registry import CONTROLLERS
    from racecav.evaluation.harness import CONTROLLERS as RESOLVED

    assert set(RESOLVED) == set(CONTROLLERS)
    for c in CONTROLLERS.values():
        assert c.args[0] in COMMANDS and COMMANDS[c.args[0]][0] == c.module
        assert importlib.util.find_spec(c.module) is not None
    assert "HOLD" not in " ".join(RESOLVED["scripted"].args)


def test_wilson_interval_holds_the_rate_at_the_ends(tmp_path):
    """200/200 once gave an upper bound of 1 - 1e-16: the chart's error bar was then negative
    and `racecav eval --table` failed after its last trial."""
    from racecav.evaluation.plots import plot_success_bars

    for n in (1, 10, 100, 200, 700, 1400, 2000):
        for k in (0, n):
            lo, hi = R.wilson(k, n)
            assert lo <= k / n <= hi
    cells = [(1.0, R.wilson(200, 200), None), (0.0, R.wilson(0, 200), None), (1.0, (0.98, 1 - 1e-16), None)]
    assert plot_success_bars([("a", cells)], ["x", "y", "z"], tmp_path / "b.png").is_file()
