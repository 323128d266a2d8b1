"""`racecav train probe`: the timing probe is at chance on two draws of the same scenario and tells the
paper-timed crossing from the conflict-timed one near the crossing (fast world). Row 16 at 4 M drives
(tests/checkpoints_support.py): the probe compares the two timings at matched speeds, and its speeds
1.5 m out overlap (the shipped avoid, row 31, reaches that point at almost one speed in each timing,
so too few samples match)."""

from __future__ import annotations

import csv

import pytest

from tests.checkpoints_support import ROW16


def _probe(tmp_path, sources: str, name: str) -> list[dict]:
    from racecav.cli import main
    from racecav.common.scenario import SCENARIOS_DIR

    out = tmp_path / f"{name}.csv"
    src = ",".join(str(SCENARIOS_DIR / f"{s}.toml") for s in sources.split(","))
    assert main(["train", "probe", "--policy", ROW16, "--sources", src, "--family", "", "--n", "512", "--distances", "1.5",
                 "--strides", "0,1", "--late-n", "0", "--out", str(out)]) == 0  # late_decision: its own test
    with out.open() as f:
        return list(csv.DictReader(f))


@pytest.mark.timeout(300)
def test_probe_is_at_chance_on_one_source_and_separates_two_timings(tmp_path):
    same = _probe(tmp_path, "left-to-right,left-to-right", "same")
    assert [int(r["stride"]) for r in same] == [0, 1]
    for r in same:  # no label leaks through ordering, seeds or normalisation
        assert int(r["per_class"]) >= 200 and float(r["probe_heldout"]) < 0.68, r
    two = _probe(tmp_path, "left-to-right,conflict-left-to-right", "two")
    for r in two:  # 1.5 m before the crossing the two timings differ in what the scan shows
        assert float(r["probe_heldout"]) > 0.8 and float(r["probe_heldout"]) > float(r["speed_alone"]) + 0.1, r


@pytest.mark.timeout(300)
def test_late_decision_planner_passes_from_the_start_and_fails_when_held_straight_too_long():
    from racecav.common.scenario import SCENARIOS_DIR
    from racecav.training.probe import late_decision

    conflict = late_decision(str(SCENARIOS_DIR / "conflict-left-to-right.toml"), "", 16, [float("inf"), 0.5], 1)
    assert conflict == {float("inf"): 1.0, 0.5: 0.0}  # a decision 0.5 m out is too late for a car timed to meet
    paper = late_decision(str(SCENARIOS_DIR / "left-to-right.toml"), "", 16, [0.5], 1)
    assert paper == {0.5: 1.0}  # the paper's timing: a straight fast ego passes ahead


@pytest.mark.timeout(300)
def test_seen_decision_frees_the_planner_where_its_straight_ego_first_sees_the_car():
    """Held straight until the car is in view: the conflict-timed car from the left comes out
    from behind the corner about 3 m out, and a decision then passes, one 10 periods (0.5 s)
    later does not. The paper-timed car stays hidden from a straight fast ego until it is through
    the crossing: the planner is freed only at the conflict point, and the straight pass wins."""
    from racecav.common.scenario import SCENARIOS_DIR
    from racecav.training.probe import seen_decision

    conflict = seen_decision(str(SCENARIOS_DIR / "conflict-left-to-right.toml"), "", 8, [0, 10], 1)
    (ok0, d0), (ok10, d10) = conflict[0], conflict[10]
    assert ok0 == 1.0 and ok10 == 0.0
    assert 2.5 < d0 < 3.5 and d10 < d0 - 1.0
    paper = seen_decision(str(SCENARIOS_DIR / "left-to-right.toml"), "", 8, [0], 1)
    ok, d = paper[0]
    assert ok == 1.0 and abs(d) < 0.2


def test_seen_filter_keeps_the_files_a_seeing_planner_passes(tmp_path):
    """`racecav train seen-filter`: held straight until 10 periods after the car is in view, the
    planner loses the conflict-timed crossing from the left and passes the paper-timed one; the
    new suite keeps only the latter (copied, with its pass rate and the filter recorded), the
    source is untouched, and scenario_sources reads the new suite."""
    import json
    import shutil

    from racecav.cli import main
    from racecav.common.scenario import SCENARIOS_DIR, scenario_sources, unfiltered

    src = tmp_path / "src"
    (src / "train").mkdir(parents=True)
    for name in ("conflict-left-to-right", "left-to-right"):
        shutil.copy(SCENARIOS_DIR / f"{name}.toml", src / "train" / f"{name}.toml")
    entries = [{"file": f"train/{n}.toml", "family": "cross-left"} for n in ("conflict-left-to-right", "left-to-right")]
    (src / "suite.json").write_text(json.dumps({"name": "src", "families": ["cross-left"],
                                                "splits": {"train": entries, "test": []}}))
    out = tmp_path / "src-seen"
    assert main(["train", "seen-filter", "--source", str(src), "--out", str(out), "--draws", "4",
                 "--delay", "10", "--keep", "0.75", "--no-progress"]) == 0
    man = json.loads((out / "suite.json").read_text())
    assert [e["file"] for e in man["splits"]["train"]] == ["train/left-to-right.toml"]
    assert man["splits"]["train"][0]["seen_pass_rate"] == 1.0 and man["seen_filter"]["delay"] == 10
    assert (out / "train" / "left-to-right.toml").read_bytes() == (src / "train" / "left-to-right.toml").read_bytes()
    assert not (out / "train" / "conflict-left-to-right.toml").exists()
    assert scenario_sources(out, "train") == [(out / "train" / "left-to-right.toml", "src-seen/cross-left")]
    assert len(json.loads((src / "suite.json").read_text())["splits"]["train"]) == 2
    assert unfiltered(str(out)) == str(src) and unfiltered(str(src)) == str(src)  # selection: the whole source
    with pytest.raises(SystemExit, match="own folder"):
        main(["train", "seen-filter", "--source", str(src), "--out", str(src)])
    with pytest.raises(SystemExit, match="no suite.json"):
        main(["train", "seen-filter", "--source", str(tmp_path / "nothing"), "--out", str(out)])


class _Steer:
    """A driver of the paper's view that ignores its scan: throttle 1 and a fixed steering action."""

    obs_stack, obs_stride, brake_below, metadata = 1, 1, None, {}

    def __init__(self, steer: float):
        self.steer = steer

    def __call__(self, obs):
        import numpy as np

        return np.tile(np.array([1.0, self.steer], np.float32), (len(obs), 1))


def test_label_fit_counts_the_steps_that_track_the_road_before_a_car_is_seen(capsys):
    """`racecav train label-fit`: a driver steering 0 follows the hold labels (the tracking steer of a
    straight ego is about 0) on the held approach; one steering 0.5 follows none, and on its own
    approach it leaves the road (no step near the crossing). Bad arguments are refused."""
    import math

    from racecav.cli import main
    from racecav.common.scenario import SCENARIOS_DIR
    from racecav.training.label_fit import BANDS, label_fit

    scen = str(SCENARIOS_DIR / "conflict-left-to-right.toml")
    straight = label_fit(_Steer(0.0), scen, n=32, steps=40)
    turning = label_fit(_Steer(0.5), scen, n=32, steps=40)
    far, mid = BANDS[0], BANDS[1]
    assert straight["held"][far][0] > 100 and straight["held"][far][1] > 0.9
    assert straight["held"][mid][1] > 0.9 and straight["own"][far][1] > 0.9
    assert turning["held"][far][0] > 100 and turning["held"][far][1] == 0.0 and turning["own"][far][1] == 0.0
    assert turning["own"][mid][0] < straight["own"][mid][0]  # it has left the road before 3 m out
    assert all(math.isnan(s) == (c == 0) for r in (straight, turning) for c, s in r["held"].values())
    assert main(["train", "label-fit", "--policy", "avoid", "--scenarios", scen, "--n", "8", "--steps", "30"]) == 0
    assert "| held |" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="--n and --steps must be >= 1"):
        main(["train", "label-fit", "--scenarios", scen, "--n", "0"])
    with pytest.raises(SystemExit, match="hold_through: cross-left is not a suite or family"):
        main(["train", "label-fit", "--scenarios", scen, "--hold-through", "cross-left", "--n", "8"])


def test_probe_drives_a_policy_with_its_brake():
    """A driver trained with a brake (brake_below) brakes in the probe's worlds as it does in its
    training env (training/select.policy_view_env): full reverse throttle stops it short of 3 m
    from the crossing, where the same action without a brake coasts on."""
    import numpy as np

    from racecav.common.scenario import SCENARIOS_DIR
    from racecav.training.probe import collect
    from racecav.training.select import ConstantAction

    src = str(SCENARIOS_DIR / "left-to-right.toml")
    coast, brake = ConstantAction(-1.0), ConstantAction(-1.0)
    brake.brake_below = -0.5
    assert np.isfinite(collect(coast, src, "", 16, [3.0], [0], 0)["speed"][3.0]).all()
    assert np.isnan(collect(brake, src, "", 16, [3.0], [0], 0)["speed"][3.0]).all()
