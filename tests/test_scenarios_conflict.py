"""Conflict-timed scenarios and the procedural suite (issue: measure avoidance, not speed).

- the actor model: triggers, synchronised arrival, release, speed changes;
- both backends move scenario actors identically for the same ego trajectory (parity, 1 mm);
- a non-evading ego collides on every conflict-timed file at any constant speed;
- the generator's files are valid, split by disjoint seeds, and reject broken family files;
- through the real services, the no-evasion references fail a generated sample.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from racecav.sim.actors import ActorBatch
from racecav.common.scenario import load_scenario, scenario_names
from racecav.evaluation import suite as S

CONFLICT = [n for n in scenario_names() if load_scenario(n).conflict_timed]
PAPER = ["right-to-left", "head-to-head", "left-to-right"]


def test_three_conflict_timed_paper_scenarios_are_shipped():
    assert sorted(CONFLICT) == sorted(f"conflict-{n}" for n in PAPER)
    for n in PAPER:  # the paper-timed ones stay clock-timed
        assert not load_scenario(n).conflict_timed


def _one(sc_name: str, seed: int = 0):
    sc = load_scenario(sc_name)
    trial = sc.sample(np.random.default_rng(seed))
    ab = ActorBatch(1, len(trial.obstacles))
    ab.load(0, trial.obstacles)
    return sc, trial, ab


@pytest.mark.parametrize("v_ego", [0.5, 1.0, 2.7])
def test_sync_meets_the_ego_at_its_point(v_ego):
    """An ego at constant speed along +x and the synchronised actor reach the centre together."""
    _sc, trial, ab = _one("conflict-right-to-left")
    x0, y0 = trial.ego[:2]
    dt, t = 0.025, 0.0
    gap_at_arrival = None
    while t < 20.0:
        ex = x0 + v_ego * t
        if round(t / dt) % 4 == 0:
            ab.control(np.array([[ex, y0, 0.0, v_ego]]))
        ab.advance(dt)
        t += dt
        if gap_at_arrival is None and x0 + v_ego * t >= 0.0:
            gap_at_arrival = math.hypot(ab.x[0, 0], ab.y[0, 0])
    assert gap_at_arrival is not None and gap_at_arrival < 0.35, gap_at_arrival


def test_trigger_waits_and_release_stops_chasing():
    _sc, trial, ab = _one("conflict-head-to-head")
    far = np.array([[-20.0, 0.0, 0.0, 1.0]])  # 20 s away: beyond the 4 s trigger
    for _ in range(40):
        ab.control(far)
        for _ in range(4):
            ab.advance(0.025)
    assert not ab.started[0, 0] and ab.s[0, 0] == 0.0
    ab.control(np.array([[-3.0, 0.0, 0.0, 1.0]]))  # 3 s away: starts, synchronised
    assert ab.started[0, 0] and not ab.released[0, 0]
    ab.control(np.array([[-0.5, 0.0, 0.0, 1.0]]))  # within the release distance: held
    v = ab.v[0, 0]
    assert ab.released[0, 0]
    ab.control(np.array([[-0.5, 0.0, 0.0, 0.05]]))  # the ego brakes: the actor is not re-timed
    assert ab.v[0, 0] == v


def test_speed_change_brakes_to_a_stop():
    from racecav.common.scenario import SpeedChange, TrialObstacle

    o = TrialObstacle(x=0.0, y=0.0, yaw=0.0, speed=1.5,
                      speed_changes=(SpeedChange(at_m=1.0, speed=0.0, accel=3.0),))
    ab = ActorBatch(1, 1)
    ab.load(0, [o])
    for _ in range(200):
        ab.advance(0.025)
    assert ab.v[0, 0] == 0.0
    assert 1.0 + 1.5 ** 2 / 6.0 - 0.05 < ab.x[0, 0] < 1.0 + 1.5 ** 2 / 6.0 + 0.05


def test_unused_actor_slots_are_parked_far_away():
    _sc, trial, _ = _one("conflict-head-to-head")
    ab = ActorBatch(1, 3)
    ab.load(0, trial.obstacles)
    assert ab.x[0, 1] > 1e5 and ab.x[0, 2] > 1e5


@pytest.mark.parametrize("name", ["conflict-right-to-left", "conflict-head-to-head", "conflict-left-to-right",
                                  "head-to-head", "right-to-left"])
def test_backends_move_actors_identically(name):
    """PyBullet and the fast world, fed the same ego trajectory (PyBullet's), place the scenario
    obstacles within 1 mm of each other at every control step."""
    from racecav.sim.bullet_world import BulletWorld
    from racecav.sim.fast_world import FastWorld

    sc = load_scenario(name)
    bw = BulletWorld(sc)
    try:
        bw.reset(seed=5)
        fw = FastWorld(n_envs=1, scenarios=[sc])
        fw.reset(seed=0)
        fw.place_trial(0, 0, bw.trial)
        # the same trial starts the same in both: ego pose and speed, obstacles
        assert np.allclose(bw.agent_state(), fw.agent_state(), atol=1e-3)
        assert np.allclose(bw.obstacles(), fw.obstacles()[:, : bw.obstacles().shape[1]], atol=1e-3)
        rng = np.random.default_rng(1)
        worst = 0.0
        for k in range(int(sc.duration_s / fw.control_period)):
            x, y, yaw, v = bw.agent_state()[0]
            fw.set_state(0, 0, x=x, y=y, yaw=yaw, v=v)
            a = np.array([[0.6 + 0.4 * math.sin(k / 7), 0.3 * rng.uniform(-1, 1)]])
            bw.step(a)
            fw.step(a)
            ob_b = bw.obstacles()[0, :, :3]
            ob_f = fw.obstacles()[0, : len(ob_b), :3]
            worst = max(worst, float(np.abs(ob_b[:, :2] - ob_f[:, :2]).max()))
            assert np.allclose(bw.obstacles()[0, :, 3], fw.obstacles()[0, : len(ob_b), 3], atol=1e-9)
        assert worst < 1e-3, worst
    finally:
        bw.close()


@pytest.mark.parametrize("name", CONFLICT)
def test_non_evading_ego_collides_at_any_constant_speed(name):
    """The invariant: straight at 0.5, 1, 1.5, 2 m/s or full throttle, a non-evading ego collides."""
    hit = S.straight_collisions([load_scenario(name)], speeds=(0.5, 1.0, 1.5, 2.0, None), trials=4, seed=11)
    assert hit.all(), hit


def test_paper_timed_side_scenarios_are_won_by_speed():
    """Why the conflict-timed versions exist: straight at full throttle passes the paper's side scenario."""
    hit = S.straight_collisions([load_scenario("right-to-left")], speeds=(None,), trials=4, seed=11)
    assert not hit.any()


@pytest.fixture(scope="module")
def small_suite(tmp_path_factory):
    out = tmp_path_factory.mktemp("suite")
    ff = S.load_families("conflicts")
    man = S.generate(ff, out, n_test=7, n_train=7, seed=3, progress=False)
    return out, man


def test_generated_suite_covers_every_family_with_disjoint_splits(small_suite):
    out, man = small_suite
    fams = S.load_families("conflicts").families
    for split in S.SPLITS:
        assert sorted(e["family"] for e in man["splits"][split]) == sorted(f.name for f in fams)
    seeds = {split: {tuple(e["seed"]) for e in man["splits"][split]} for split in S.SPLITS}
    assert not seeds["train"] & seeds["test"]
    for e in man["splits"]["test"]:
        sc = load_scenario(out / e["file"])
        assert sc.conflict_timed or e["family"] == "stopped"
    assert json.loads((out / "suite.json").read_text()) == man


def test_a_split_written_alone_is_the_one_both_write(small_suite, tmp_path):
    """`--splits test` (what `racecav eval --table` writes when the suite is missing) writes the
    same test files as a full generation; the train split, absent, is an error naming the command
    that writes it, and writing it later keeps the test split."""
    from racecav.common.scenario import open_suite

    full, man = small_suite
    ff = S.load_families("conflicts")
    alone = S.generate(ff, tmp_path, n_test=7, n_train=7, seed=3, progress=False, splits=("test",))
    assert list(alone["splits"]) == ["test"] and alone["splits"]["test"] == man["splits"]["test"]
    for e in man["splits"]["test"]:
        assert (tmp_path / e["file"]).read_text() == (full / e["file"]).read_text()
    with pytest.raises(ValueError, match="no train split .*--splits train"):
        open_suite(str(tmp_path)).files("train")
    both = S.generate(ff, tmp_path, n_test=7, n_train=7, seed=3, progress=False, splits=("train",))
    assert both["splits"] == man["splits"]


def test_generated_files_make_a_straight_car_collide(small_suite):
    from racecav.common.scenario import scenario_files

    files = scenario_files(small_suite[0], "test")
    hit = S.straight_collisions([load_scenario(f) for f in files], trials=3, seed=99)
    assert hit.all(), [f.name for f, h in zip(files, hit) if not h.all()]


def test_scenario_sources_name_each_file_s_family(small_suite):
    """The curriculum's groups: a suite's manifest family (per suite), a plain file's stem."""
    from racecav.common.scenario import SCENARIOS_DIR, scenario_sources

    out, man = small_suite
    plain = SCENARIOS_DIR / "conflict-head-to-head.toml"
    got = scenario_sources(f"{out},{plain}", "train")
    assert got[:-1] == [(out / e["file"], f"{out.name}/{e['family']}") for e in man["splits"]["train"]]
    assert got[-1] == (plain, "conflict-head-to-head")


def test_generation_is_reproducible(small_suite, tmp_path):
    out, _ = small_suite
    ff = S.load_families("conflicts")
    S.generate(ff, tmp_path, n_test=7, n_train=1, seed=3, progress=False)
    for f in sorted((out / "test").glob("*.toml")):
        assert f.read_text().split("\n", 1)[1] == (tmp_path / "test" / f.name).read_text().split("\n", 1)[1]


def test_paper_timed_family_meets_an_ego_holding_its_start_speed(tmp_path):
    """timing = "paper": each actor reaches its conflict point when the ego at its start speed
    does, its start delay later; so a straight ego at its start speed collides with the crossing
    cars, while full throttle passes ahead of them (the paper's side scenarios)."""
    from racecav.common.scenario import scenario_sources

    ff = S.load_families("paper-timed")
    man = S.generate(ff, tmp_path, n_test=3, n_train=24, seed=5, progress=False)
    assert {e["family"] for e in man["splits"]["train"]} == {"cross-left", "cross-right", "head-on"}
    crossings = []
    for f, fam in scenario_sources(tmp_path, "train"):
        sc = load_scenario(f)
        ego, (o,) = sc.ego, sc.obstacles
        t_ego = -ego.x / ego.speed  # its conflict point is at x = 0
        t_actor = math.hypot(o.x, o.y - ego.y) / o.speed + o.start.value
        assert o.start.kind == "time" and 0.0 <= o.start.value <= 0.3
        assert t_actor == pytest.approx(t_ego + o.start.value, abs=0.01), f.name
        if not fam.endswith("head-on"):
            crossings.append(sc)
    full_throttle = S.straight_collisions(crossings, speeds=(None,), trials=2, seed=3)
    assert not full_throttle.any(), full_throttle
    # the same files with the actor delay removed, against a straight ego at exactly its start speed
    at_start = [sc.model_copy(update={"randomize": sc.randomize.model_copy(update={
        "ego_speed": 0.0, "ego_xy": 0.0, "ego_yaw_deg": 0.0, "obstacle_xy": 0.0, "obstacle_yaw_deg": 0.0})})
        for sc in crossings]
    hits = [S.straight_collisions([sc], speeds=(sc.ego.speed,), trials=1, seed=3)[0, 0] for sc in at_start]
    assert all(hits), hits


def test_open_suite_is_a_free_road_that_a_straight_ego_drives_through(tmp_path):
    """kind = "empty": no actor, the drawn episode length; a straight ego at full throttle meets
    every file's progress in its time, one at 1 m/s none (so a detour shows as a failure)."""
    from racecav.common.scenario import scenario_sources

    ff = S.load_families("open")
    S.generate(ff, tmp_path, n_test=2, n_train=12, seed=5, progress=False)
    scs = [load_scenario(f) for f, _ in scenario_sources(tmp_path, "train")]
    assert len(scs) == 12 and all(not sc.obstacles for sc in scs)
    lo, hi = ff.common.duration_s
    assert all(lo <= sc.duration_s <= hi for sc in scs), [sc.duration_s for sc in scs]
    from racecav.common.vehicle import load_car, throttle_for_speed
    from racecav.sim.fast_world import FastWorld

    car = load_car()
    for thr, passes in ((1.0, True), (float(throttle_for_speed(1.0, car, car.agent_speed_scale)), False)):
        fw = FastWorld(n_envs=len(scs), scenarios=scs, car=car, seed=3)
        fw.scenario_of_env = np.arange(len(scs))
        fw.reset()
        live = np.ones(len(scs), bool)
        success = np.zeros(len(scs), bool)
        while live.any():  # each world's verdict (FastWorld.success) when its time is up
            _, _, c, _ = fw.step(np.tile([thr, 0.0], (len(scs), 1)))
            assert not (c & live).any()
            ended = live & (fw.time >= fw.time_limit - 1e-9)
            success[ended] = fw.success()[ended]
            live &= ~ended
        assert (success == passes).all(), (thr, fw.progress())


def test_empty_family_is_refused_in_a_benchmark(tmp_path):
    p = tmp_path / "fam.toml"
    p.write_text((S.SUITES_DIR / "open.toml").read_text().replace("validate = false", "validate = true"))
    with pytest.raises(ValueError, match="empty"):
        S.load_families(p)


def test_paper_timing_is_for_crossing_and_head_on_kinds(tmp_path):
    text = (S.SUITES_DIR / "paper-timed.toml").read_text()
    p = tmp_path / "fam.toml"
    p.write_text(text.replace('kind = "head_on"', 'kind = "stopped"', 1))
    with pytest.raises(ValueError, match="timing"):
        S.load_families(p)


@pytest.mark.parametrize("edit,field", [
    ('angle_deg = [45.0, 135.0]       # actor heading', "angle_deg"),
    ('kind = "crossing"', "kind"),
    ('obstacle_speed = [0.5, 2.0]', "obstacle_speed"),
])
def test_broken_family_file_names_the_field(tmp_path, edit, field):
    text = (S.SUITES_DIR / "conflicts.toml").read_text()
    bad = {"angle_deg": 'angle_deg = [150.0, 30.0]       # actor heading',
           "kind": 'kind = "teleport"',
           "obstacle_speed": 'obstacle_speed = [2.0, "fast"]'}[field]
    p = tmp_path / "fam.toml"
    p.write_text(text.replace(edit, bad, 1))
    with pytest.raises(ValueError, match=field):
        S.load_families(p)


def test_missing_family_file_and_suite_are_named(tmp_path):
    with pytest.raises(ValueError, match="not found"):
        S.load_families(tmp_path / "nope.toml")
    from racecav.common.scenario import open_suite

    with pytest.raises(ValueError, match="racecav suite generate"):
        open_suite(tmp_path / "nothing-here")


@pytest.mark.parametrize("old,new,field", [
    ("speed_min = 0.5", "speed_min = 3.0", "speed_min"),
    ('kind = "time_to_arrival"', 'kind = "whenever"', "start.kind"),
    ("value = 4.0", "value = -1.0", "start.value"),
    ("[obstacles.start]", "delay_s = 1.0\n[obstacles.start]", "delay_s"),
])
def test_broken_conflict_scenario_names_the_field(tmp_path, old, new, field):
    from racecav.common.scenario import SCENARIOS_DIR

    text = (SCENARIOS_DIR / "conflict-head-to-head.toml").read_text()
    assert old in text
    p = tmp_path / "bad.toml"
    p.write_text(text.replace(old, new, 1))
    with pytest.raises(ValueError, match=field):
        load_scenario(p)


def test_suite_cli_generates_and_lists(tmp_path):
    out = tmp_path / "s"
    r = subprocess.run([sys.executable, "-m", "racecav.cli", "suite", "generate", "--n", "7", "--n-train", "7",
                        "--out", str(out), "--no-progress"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "test: 7 files" in r.stdout
    r = subprocess.run([sys.executable, "-m", "racecav.cli", "suite", "list", str(out)], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0 and "train: 7 files" in r.stdout
    r = subprocess.run([sys.executable, "-m", "racecav.cli", "suite", "generate", "--families",
                        str(tmp_path / "missing.toml"), "--out", str(out)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "missing.toml" in r.stdout + r.stderr


@pytest.mark.timeout(600)
def test_no_evasion_references_fail_the_suite_through_the_services(small_suite, tmp_path):
    """Through router + sim + scripted controller: straight at 1 m/s and at full throttle, the
    generated sample's conflicts collide (the suite measures avoidance, not speed)."""
    out, _ = small_suite
    for ctrl in ("scripted", "full-throttle"):
        js = tmp_path / f"{ctrl}.json"
        r = subprocess.run([sys.executable, "-m", "racecav.cli", "eval", "--suite", str(out), "--controller", ctrl,
                            "--trials-per-scenario", "2", "--out-dir", str(tmp_path / "ev"), "--json", str(js),
                            "--no-progress"], capture_output=True, text=True, timeout=500)
        assert r.returncode == 0, r.stdout + r.stderr
        doc = json.loads(js.read_text())
        assert doc["complete"] and doc["summary"]["trials"] == 14
        assert set(doc["families"]) == {f.name for f in S.load_families("conflicts").families}
        assert doc["summary"]["successes"] <= 1, doc["families"]
        assert js.with_suffix(".png").is_file()


def _contact_step(world_step, n_steps, actions):
    for k in range(n_steps):
        if world_step(actions[k]):
            return k
    return None


@pytest.mark.parametrize("name", ["conflict-right-to-left", "conflict-head-to-head", "conflict-left-to-right",
                                  "head-to-head"])
def test_scenario_contact_step_parity(name):
    """Recorded action sequences (straight at 1 m/s, at full throttle, and the shipped reversed
    policy's actions recorded in PyBullet) replayed open loop in both backends: the contact
    happens in the same control step, give or take one."""
    from racecav.common.vehicle import load_car, throttle_for_speed
    from racecav.common.policy import load_policy
    from racecav.sim.bullet_world import BulletWorld
    from racecav.sim.fast_world import FastWorld

    sc = load_scenario(name)
    car = load_car()
    n = int(round(sc.duration_s / car.control_period_s))
    t1 = float(throttle_for_speed(1.0, car, car.agent_speed_scale))
    bw = BulletWorld(sc)
    try:
        bw.reset(seed=2)
        pol, recorded, obs = load_policy("reversed"), [], bw._observe()
        for _ in range(n):  # the policy in PyBullet: its actions and its contact step
            a = pol(obs)
            recorded.append(a)
            obs, _, col, _ = bw.step(a)
            obs = obs[0]
            if col[0]:
                break
        recorded += [np.zeros(2)] * (n - len(recorded))
        for seq in (np.tile([t1, 0.0], (n, 1)), np.tile([1.0, 0.0], (n, 1)), np.array(recorded)):
            bw.reset(seed=2)
            trial = bw.trial
            kb = _contact_step(lambda a: bool(bw.step(a)[2][0]), n, seq)
            fw = FastWorld(n_envs=1, scenarios=[sc])
            fw.reset(seed=0)
            fw.place_trial(0, 0, trial)
            kf = _contact_step(lambda a: bool(fw.step(a[None])[2][0]), n, seq)
            assert (kb is None) == (kf is None), (kb, kf)
            if kb is not None:
                assert abs(kb - kf) <= 1, (kb, kf)
    finally:
        bw.close()


def test_overtake_env_runs_scenario_episodes_on_both_backends():
    import gymnasium as gym
    from gymnasium.utils.env_checker import check_env

    import racecav.training  # noqa: F401
    from racecav.common.scenario import SCENARIOS_DIR

    for backend in ("fast", "bullet"):
        env = gym.make("racecav/Overtake-v0", backend=backend, scenarios=str(SCENARIOS_DIR / "conflict-head-to-head.toml"),
                       obs_stack=2)
        check_env(env.unwrapped, skip_render_check=True)
        obs, _ = env.reset(seed=1)
        assert obs.shape == (340,) and np.array_equal(obs[:170], obs[170:])
        for _ in range(200):
            obs, r, term, trunc, info = env.step(np.array([1.0, 0.0]))
            if term or trunc:
                break
        assert term and info["is_success"] is False  # straight at full throttle: the conflict is real
        env.close()
