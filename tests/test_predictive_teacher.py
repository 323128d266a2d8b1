"""The predictive teacher (training/predictive_teacher.py) driven by its own labels in the fast
world, on validated draws of the roads generator (evaluation/benchmark.py): the draws of a
conflict family make both non-evading references collide every time, by construction."""

from __future__ import annotations

import numpy as np
import pytest

from racecav.common.scenario import load_scenario, open_suite
from racecav.evaluation.benchmark import generate, load_benchmark
from racecav.training.predictive_teacher import SELECTION_SEED, drive

FAMILIES = ("from-rest", "stop-short", "rear-stationary", "rear-braking", "braking")
TRIALS = 2


@pytest.fixture(scope="module")
def suite(tmp_path_factory):
    bf = load_benchmark("roads")
    bf = bf.model_copy(update={"families": [f for f in bf.families if f.name in FAMILIES]})
    out = tmp_path_factory.mktemp("roads")
    generate(bf, out, seed=0, splits=("test", "controls"), progress=False, n_test=2)
    return open_suite(out)


def scenarios(suite, split: str, family: str) -> list:
    return [load_scenario(f) for f, fam in suite.files(split) if fam == family]


def test_drives_off_from_rest_at_once(suite):
    scs = scenarios(suite, "controls", "from-rest")
    r = drive(scs, TRIALS, SELECTION_SEED, "teacher")
    assert r["from_rest"].all()
    assert (r["drive_off"] <= 1.0).all(), r["drive_off"]
    assert r["success"].all()


@pytest.mark.parametrize("family", ["rear-stationary", "rear-braking", "braking"])
def test_passes_what_both_references_crash_into(suite, family):
    scs = scenarios(suite, "test", family)
    for ref in ("straight", "full"):
        assert drive(scs, TRIALS, SELECTION_SEED, ref)["collided"].all(), ref
    r = drive(scs, TRIALS, SELECTION_SEED, "teacher")
    assert r["success"].all(), r


def test_does_not_wait_for_a_car_that_stops_short(suite):
    scs = scenarios(suite, "controls", "stop-short")
    r = drive(scs, TRIALS, SELECTION_SEED, "teacher")
    ref = drive(scs, TRIALS, SELECTION_SEED, "straight")
    assert r["success"].all()
    # through sooner than a car that drives on at 1 m/s: it never stopped to wait
    assert (r["done_at"] < ref["done_at"]).all(), (r["done_at"], ref["done_at"])
    assert np.isfinite(r["done_at"]).all()


def test_reacts_only_to_cars_its_lidar_has_seen(suite, monkeypatch):
    """The teacher predicts only the actors the ego's scan returned from (within SEEN_MEMORY_S):
    its labels never answer a car the policy cannot see. Blinded, it drives into the stationary
    car it passes when it sees it."""
    from racecav.common.vehicle import load_car
    from racecav.sim.fast_world import FastWorld
    from racecav.training import predictive_teacher as PT

    scs = scenarios(suite, "test", "rear-stationary")
    fw = FastWorld(n_envs=2, scenarios=scs[:1], car=load_car(), seed=SELECTION_SEED)
    fw.reset()
    teacher = PT.PredictiveTeacher(fw)
    teacher.labels()
    pose = np.stack([fw.x[:, 0], fw.y[:, 0], fw.yaw[:, 0]], 1)
    assert (teacher.w.actors.used == fw.seen_by_agent(np.arange(2), pose=pose)).all()
    assert teacher.w.actors.used.any(1).all()  # the car ahead is in view from the start
    monkeypatch.setattr(PT.Batch, "seen", lambda self: np.zeros(self.actors.used.shape, bool))
    assert drive(scs, TRIALS, SELECTION_SEED, "teacher")["collided"].all()


def test_sees_with_the_students_lidar_view():
    """The probe's world scans with the student's view (VIEW, the shipped avoid's wide scan): a
    car crossing from the side at a bearing of 50-60 deg, outside the paper's frontal +-45 deg
    for its whole approach, is one the student sees and the teacher must answer. Scanning with
    the paper's view, the teacher never saw it and drove into it at full throttle."""
    from pathlib import Path

    from racecav.training.predictive_teacher import VIEW, student_car

    assert VIEW == "wide"
    scs = [load_scenario(Path(__file__).parent / "data" / "roads_braking_side_approach.toml")]
    assert drive(scs, TRIALS, SELECTION_SEED, "teacher", car=student_car("paper"))["collided"].all()
    r = drive(scs, TRIALS, SELECTION_SEED, "teacher")
    assert r["success"].all(), r


def test_a_policy_drives_beside_its_teacher_on_the_same_trials(suite):
    """--policy: a student on its own stacked scans, measured as the teacher is. A policy that
    always brakes stands in every controls trial (frozen, no contact); one that always drives
    at full throttle straight ahead passes the controls as the full-throttle reference does."""
    from racecav.common.policy import NumpyPolicy

    def constant(a_t: float) -> NumpyPolicy:
        arrays = {"w0": np.zeros((2 * 169, 4)), "b0": np.zeros(4), "w1": np.zeros((4, 4)), "b1": np.zeros(4),
                  "w2": np.zeros((4, 2)), "b2": np.array([a_t, 0.0])}
        return NumpyPolicy(arrays, {"obs_stack": 2, "obs_stride": 4, "lidar": "wide", "brake_below": -0.5})

    scs = scenarios(suite, "controls", "from-rest")
    stand = drive(scs, TRIALS, SELECTION_SEED, "policy", policy=constant(-1.0))
    assert stand["frozen"].all() and not stand["collided"].any()
    assert np.isnan(stand["drive_off"]).all()
    go = drive(scs, TRIALS, SELECTION_SEED, "policy", policy=constant(1.0))
    full = drive(scs, TRIALS, SELECTION_SEED, "full")
    assert (go["drive_off"] <= 1.0).all()
    assert go["success"].tolist() == full["success"].tolist()
    with pytest.raises(ValueError, match="policy driver"):
        drive(scs, TRIALS, SELECTION_SEED, "policy")
