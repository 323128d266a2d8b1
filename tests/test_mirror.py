"""The mirror teacher of ``racecav train dagger --expert mirror`` (training/mirror.py)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from racecav.common.config import EnvConfig
from racecav.common.scenario import SCENARIOS_DIR
from racecav.training.mirror import MirrorTeacher, mirror_action, mirror_scans
from racecav.training.vec_env import FastVecEnv
from tests.checkpoints_support import ROW16


def row31():
    """Row 31 at 5 M (the avoid shipped until 2026-12-05; two consecutive wide scans, no brake): the
    frozen policy these teacher tests relabel, whose behaviour they were written against."""
    from racecav.training.select import COMMITTED, checkpoint_policy

    return checkpoint_policy(COMMITTED / "avoid-gsde-flow120" / "checkpoints" / "step_005005312.zip")


def test_mirror_reverses_each_stacked_scan_and_negates_the_steering():
    obs = np.arange(2 * 2 * 5, dtype=np.float32).reshape(2, 10)  # 2 observations of 2 scans x 5 rays
    m = mirror_scans(obs, obs_stack=2)
    assert m[0].tolist() == [4, 3, 2, 1, 0, 9, 8, 7, 6, 5]
    assert np.array_equal(mirror_scans(m, 2), obs)
    a = np.array([[0.5, 0.2], [1.0, -1.0]], np.float32)
    assert np.array_equal(mirror_action(a), np.array([[0.5, -0.2], [1.0, 1.0]], np.float32))
    assert a[0, 1] == np.float32(0.2)  # a copy


@pytest.fixture
def crossings(tmp_path):
    """A scenario folder with the paper's two side scenarios (families left-to-right, right-to-left)."""
    folder = tmp_path / "scenarios"
    folder.mkdir()
    for name in ("left-to-right", "right-to-left"):
        shutil.copy(SCENARIOS_DIR / f"{name}.toml", folder / f"{name}.toml")
    return folder


def test_teacher_mirrors_only_a_mirrored_family_with_a_car_near_on_the_left(crossings):
    """Label = the policy's own action, except in the left-to-right worlds once their car is
    within reach on the ego's left: there the policy's action on the mirrored scans, mirrored."""
    policy = row31()
    env = FastVecEnv(config=EnvConfig(n_envs=16, scenarios=str(crossings), scenario_share=1.0, n_obstacles=0,
                                      lidar="wide", obs_stack=2), seed=3)
    teacher = MirrorTeacher(policy, env, ["left-to-right"])
    env.reset()
    (world,) = env.worlds
    fam = np.array(world.scenario_families)[world.scenario_index]
    assert {"left-to-right", "right-to-left"} <= set(fam)
    seen_mirrored = np.zeros(env.num_envs, bool)
    for _ in range(25):  # 2.5 s: the left car comes within NEAR_M
        raw = env._stacked()
        labels, mirrored = teacher.labels(raw)
        assert not mirrored[fam != "left-to-right"].any()
        own = policy(raw)
        assert np.array_equal(labels[~mirrored], own[~mirrored])
        if mirrored.any():
            want = mirror_action(policy(mirror_scans(raw[mirrored], 2)))
            assert np.allclose(labels[mirrored], want, atol=1e-6)
            assert not np.allclose(labels[mirrored], own[mirrored], atol=1e-3)  # the policy is not symmetric
        seen_mirrored |= mirrored
        env.step(np.tile(np.array([0.2, 0.0], np.float32), (env.num_envs, 1)))
    assert seen_mirrored[fam == "left-to-right"].all()
    env.close()

    # the anchors: the mirror image of that mask, in the anchor families
    env = FastVecEnv(config=EnvConfig(n_envs=16, scenarios=str(crossings), scenario_share=1.0, n_obstacles=0,
                                      lidar="wide", obs_stack=2), seed=3)
    teacher = MirrorTeacher(policy, env, ["left-to-right"], anchor_families=["right-to-left"])
    env.reset()
    seen_anchored = np.zeros(env.num_envs, bool)
    for _ in range(25):
        anchored = teacher.anchored()
        assert not anchored[fam != "right-to-left"].any() and not (anchored & teacher.mirrored()).any()
        seen_anchored |= anchored
        env.step(np.tile(np.array([0.2, 0.0], np.float32), (env.num_envs, 1)))
    assert seen_anchored[fam == "right-to-left"].all()
    env.close()


def test_teacher_names_a_family_the_scenarios_lack(crossings):
    env = FastVecEnv(config=EnvConfig(n_envs=4, scenarios=str(crossings), scenario_share=1.0, n_obstacles=0,
                                      lidar="wide", obs_stack=2), seed=0)
    with pytest.raises(ValueError, match=r"cross-left.*left-to-right', 'right-to-left"):
        MirrorTeacher(row31(), env, ["cross-left"])
    env.close()


def test_dagger_with_the_mirror_teacher_runs_and_refuses_a_wrong_family(tmp_path, crossings, capsys):
    import json

    from racecav.cli import main

    base = ["train", "dagger", "--no-progress", "--preset", "fast", "--n-envs", "8", "--n-steps", "8",
            "--checkpoint-every", "64", "--grad-steps", "2", "--batch-size", "32", "--n-obstacles", "0",
            "--scenarios", str(crossings), "--scenario-share", "1.0", "--obs-stack", "2", "--lidar", "wide",
            "--init-from", ROW16, "--expert", "mirror"]
    run = tmp_path / "run"
    assert main(base + ["--run-dir", str(run), "--mirror-families", "left-to-right", "--steps", "128"]) == 0
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["expert"] == "mirror" and cfg["mirror_families"] == "left-to-right"
    rows = (run / "progress.csv").read_text().splitlines()
    assert len(rows) == 3 and float(rows[-1].split(",")[3]) >= 0.0  # loss column
    assert main(base + ["--run-dir", str(tmp_path / "bad"), "--mirror-families", "cross-left", "--steps", "64"]) == 2
    assert "--mirror-families" in capsys.readouterr().out


def test_mirrored_policy_is_an_involution_and_the_mirror_table_is_written(tmp_path, crossings):
    """Mirroring twice gives the policy back; ``racecav train mirror`` writes the policy, its
    mirror image and the two non-evading references as rows of one table."""
    from racecav.cli import main
    from racecav.training.mirror import MirroredPolicy

    policy = row31()
    scans = np.random.default_rng(0).uniform(0.2, 10.0, (32, policy.obs_dim)).astype(np.float32)
    twice = MirroredPolicy(MirroredPolicy(policy))
    assert np.allclose(twice(scans), policy(scans), atol=1e-6)
    assert not np.allclose(MirroredPolicy(policy)(scans), policy(scans), atol=1e-3)
    out = tmp_path / "mirror.md"
    assert main(["train", "mirror", "--policy", "avoid", "--trials", "1", "--suite-episodes", "8", "--out", str(out),
                 "--suite", str(crossings), "--paper-suite", str(crossings), "--mirror-families", "left-to-right"]) == 0
    rows = [r for r in out.read_text().splitlines() if r.startswith("| ") and not r.startswith("| driver")]
    assert [r.split(" | ")[0] for r in rows] == [
        "| avoid", "| avoid, mirrored", "| avoid until a car is near on its left, then mirrored (`--expert mirror`)",
        "| avoid until a car is seen near on its left, then mirrored (`--expert mirror --mirror-seen`)",
        "| *straight 1 m/s* (no evasion)", "| *straight, full throttle* (no evasion)"]
    # the teachers read the fast world's cars: suite columns only, no PyBullet cells
    for r in rows[2:4]:
        cells = r.split(" | ")[1:]
        assert cells[:6] == ["-"] * 6 and cells[6].endswith("%")
    with pytest.raises(SystemExit, match="cross-left"):  # a family the suites lack
        main(["train", "mirror", "--policy", "avoid", "--trials", "1", "--suite-episodes", "8",
              "--suite", str(crossings), "--paper-suite", str(crossings)])
    with pytest.raises(SystemExit, match="--trials"):
        main(["train", "mirror", "--policy", "avoid", "--trials", "0"])


def test_ppo_imitation_term_with_the_mirror_teacher(tmp_path, crossings, capsys):
    """``racecav train overtake --bc-coef C --expert mirror``: PPO plus the fit to the frozen
    --init-from policy, its mirrored action at every step the teacher mirrors and its own action
    (the anchors) at --bc-label-steps steps of each rollout; refused without --init-from."""
    import csv

    from stable_baselines3 import PPO

    from racecav.cli import main
    from racecav.training.imitation_term import make_callback
    from racecav.training.runs import load_run_config
    from racecav.training.train import make_venv

    flags = ["--preset", "fast", "--n-envs", "8", "--n-steps", "8", "--batch-size", "32", "--n-epochs", "1",
             "--checkpoint-every", "64", "--n-obstacles", "0", "--scenarios", str(crossings),
             "--scenario-share", "1.0", "--obs-stack", "2", "--lidar", "wide", "--bc-coef", "1",
             "--bc-grad-steps", "2", "--expert", "mirror", "--mirror-families", "left-to-right"]
    run = tmp_path / "run"
    assert main(["train", "overtake", "--no-progress", "--run-dir", str(run), "--steps", "192",
                 "--init-from", ROW16, "--bc-label-steps", "0", *flags]) == 0
    with (run / "imitation.csv").open() as f:
        rows = list(csv.DictReader(f))
    # no anchors: every label is a mirrored one
    assert rows and int(rows[-1]["labels"]) > 0 and all(float(r["manoeuvres"]) == 1.0 for r in rows), rows

    for anchors, anchor_families, seen in ((0, "", False), (2, "", False), (0, "right-to-left", False), (0, "", True)):
        tc = load_run_config(run)[0].model_copy(update={"bc_label_steps": anchors, "anchor_families": anchor_families,
                                                         "mirror_seen": seen})
        venv = make_venv(tc, seed=5)
        cb = make_callback(tmp_path, tc, venv, seed=0)
        assert cb.teacher.seen_only == seen  # --mirror-seen reaches the teacher
        samples = 256 if seen else 64  # a seen car comes later: the corners hide it at first
        PPO("MlpPolicy", venv, n_steps=8, batch_size=32, n_epochs=1, device="cpu").learn(samples, callback=cb)
        obs, act, mirrored = cb.obs[:cb.size], cb.act[:cb.size], cb.man[:cb.size]
        # the left-to-right worlds once their car is near, plus 8 worlds at each anchor step, plus
        # the right-to-left worlds once their car is near on the right
        assert 0 < mirrored.sum() and cb.size < samples
        assert (~mirrored).sum() <= (8 * anchors if not anchor_families else 64)
        assert (~mirrored).any() == (anchors > 0 or bool(anchor_families))
        teacher = cb.teacher.policy
        mirrored_label = mirror_action(teacher(mirror_scans(obs[mirrored], 2)))
        # labels as the car acts: the teacher's steering saturates beyond the car's range. float32
        # rounding differs with the batch's shape (a few 1e-6); a wrong label is off by ~0.1
        assert np.allclose(act[mirrored], np.clip(mirrored_label, cb.lo, cb.hi), atol=2e-5)
        assert np.allclose(act[~mirrored], np.clip(teacher(obs[~mirrored]), cb.lo, cb.hi), atol=2e-5)

    assert main(["train", "overtake", "--no-progress", "--run-dir", str(tmp_path / "bad"), "--steps", "64",
                 *flags]) == 2
    assert "--expert mirror needs --init-from" in capsys.readouterr().out
    track = [f if f != "mirror" else "track" for f in flags]  # the message names the expert given
    assert main(["train", "overtake", "--no-progress", "--run-dir", str(tmp_path / "bad2"), "--steps", "64",
                 *track]) == 2
    assert "--expert track needs --init-from" in capsys.readouterr().out


def _blocked(p, q, walls) -> bool:
    """The segment p -> q crosses one of the wall centre lines (x0, y0, x1, y1)."""
    def side(a, b, c):
        return np.sign((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))
    return any(side(p, q, w[:2]) * side(p, q, w[2:]) < 0 and side(w[:2], w[2:], p) * side(w[:2], w[2:], q) < 0
               for w in walls)


def test_track_teacher_labels_full_throttle_tracking_where_a_seen_car_is_near_on_the_left(crossings):
    """--expert track: on the steps the mirror teacher would mirror (seen_only), the label is full
    throttle and the tracking steer of the ego's road (training/expert.tracking_steer); the
    policy's own action elsewhere."""
    from racecav.training.expert import tracking_steer

    policy = row31()
    env = FastVecEnv(config=EnvConfig(n_envs=16, scenarios=str(crossings), scenario_share=1.0, n_obstacles=0,
                                      lidar="wide", obs_stack=2), seed=3)
    teacher = MirrorTeacher(policy, env, ["left-to-right"], seen_only=True, relabel="track")
    with pytest.raises(ValueError, match="relabel"):
        MirrorTeacher(policy, env, ["left-to-right"], relabel="straight")
    env.reset()
    (world,) = env.worlds
    fam = np.array(world.scenario_families)[world.scenario_index]
    ever = np.zeros(env.num_envs, bool)
    rng = np.random.default_rng(0)
    for _ in range(25):
        raw = env._stacked()
        labels, mask = teacher.labels(raw)
        assert not mask[fam != "left-to-right"].any()
        assert np.array_equal(mask, teacher.mirrored())
        assert np.array_equal(labels[~mask], policy(raw)[~mask])
        if mask.any():
            assert (labels[mask, 0] == 1.0).all()
            assert np.allclose(labels[mask, 1], tracking_steer(world)[mask])
            assert world.seen_by_agent(np.flatnonzero(mask)).any(axis=1).all()
        ever |= mask
        # a weaving ego: the tracking steer is not zero
        env.step(np.stack([np.full(env.num_envs, 0.2), rng.uniform(-0.3, 0.3, env.num_envs)], 1).astype(np.float32))
    assert ever[fam == "left-to-right"].any()
    env.close()


def test_hold_teacher_labels_tracking_until_a_car_has_been_seen_before_the_crossing(crossings):
    """--expert hold: in a world of the given families, full throttle and the tracking steer on
    every step before any car has been in the ego's scan this episode (latched, cleared by a new
    episode) while the ego is short of the crossing's centre; the policy's own action elsewhere."""
    from racecav.training.expert import tracking_steer

    policy = row31()
    env = FastVecEnv(config=EnvConfig(n_envs=16, scenarios=str(crossings), scenario_share=1.0, n_obstacles=0,
                                      lidar="wide", obs_stack=2), seed=5)
    with pytest.raises(ValueError, match="mirror-seen"):
        MirrorTeacher(policy, env, ["left-to-right"], seen_only=True, relabel="hold")
    teacher = MirrorTeacher(policy, env, ["left-to-right"], relabel="hold")
    (world,) = env.worlds
    rng = np.random.default_rng(1)
    for episode in range(2):
        env.reset()
        latch = np.zeros(env.num_envs, bool)  # reference: seen at any step so far
        released = np.zeros(env.num_envs, bool)
        for k in range(40):
            raw = env._stacked()
            fam = np.array(world.scenario_families)[world.scenario_index]  # an auto-reset draws anew
            latch &= world.time > 0  # ... and starts with nothing seen
            latch |= world.seen_by_agent(np.arange(env.num_envs)).any(axis=1)
            labels, mask = teacher.labels(raw)
            expect = (fam == "left-to-right") & ~latch & (world.x[:, 0] < 0.0)
            assert np.array_equal(mask, expect), k
            if k == 0:  # nothing is in view at the start: the car is behind the corner
                assert mask[fam == "left-to-right"].all()
            assert np.array_equal(labels[~mask], policy(raw)[~mask])
            assert (labels[mask, 0] == 1.0).all()
            assert np.allclose(labels[mask, 1], tracking_steer(world)[mask])
            released |= (fam == "left-to-right") & latch & (world.x[:, 0] < 0.0)
            # a slow weaving ego: it sees the car before the crossing, and the steer is not zero
            env.step(np.stack([np.full(env.num_envs, 0.1), rng.uniform(-0.3, 0.3, env.num_envs)], 1).astype(np.float32))
        assert released.any()  # a car seen short of the crossing ends the labels there
    env.close()


def test_seen_cars_are_the_ones_in_line_of_sight_and_the_teacher_labels_only_those(crossings):
    """FastWorld.seen_by_agent against plain line of sight: a car whose four corners are all
    behind a wall is never seen, one whose centre is in clear view well inside the field of view
    always is; the teacher with seen_only mirrors a subset of its near steps, each with its car
    seen, and the corners hide the crossing car for part of the approach."""
    from racecav.common.world import load_world

    walls = load_world("intersection").walls
    policy = row31()
    env = FastVecEnv(config=EnvConfig(n_envs=16, scenarios=str(crossings), scenario_share=1.0, n_obstacles=0,
                                      lidar="wide", obs_stack=2), seed=3)
    near_only = MirrorTeacher(policy, env, ["left-to-right"])
    seen_only = MirrorTeacher(policy, env, ["left-to-right"], seen_only=True)
    env.reset()
    (w,) = env.worlds
    hidden = clear = hidden_near = 0
    for _ in range(25):
        seen = w.seen_by_agent(np.arange(w.x.shape[0]))
        c, s = np.cos(w.yaw[:, 0]), np.sin(w.yaw[:, 0])
        for n in range(w.x.shape[0]):
            lidar = (w.x[n, 0] + c[n] * w.mount[0] - s[n] * w.mount[1], w.y[n, 0] + s[n] * w.mount[0] + c[n] * w.mount[1])
            car = (w.x[n, 1], w.y[n, 1])
            bearing = np.arctan2(car[1] - lidar[1], car[0] - lidar[0]) - w.yaw[n, 0]
            if all(_blocked(lidar, corner, walls) for corner in w.corners[n, 1]):
                assert not seen[n, 0]
                hidden += 1
            elif (not _blocked(lidar, car, walls) and abs(np.angle(np.exp(1j * bearing))) < 1.2
                  and np.hypot(car[0] - lidar[0], car[1] - lidar[1]) < 8
                  and min(np.hypot(*(np.r_[e] - lidar)) for e in walls.reshape(-1, 2)) > 0.3):
                assert seen[n, 0]
                clear += 1
        a, b = near_only.mirrored(), seen_only.mirrored()
        assert not (b & ~a).any()
        hidden_near += int((a & ~b).sum())
        env.step(np.tile(np.array([0.2, 0.0], np.float32), (env.num_envs, 1)))
    assert hidden > 0 and clear > 0 and hidden_near > 0
    env.close()


def test_the_imitation_fit_can_use_its_own_optimizer(tmp_path, crossings):
    """--bc-learning-rate: the fit steps an Adam of its own on the actor; PPO's optimizer state
    and the critic stay as they were."""
    import torch
    from stable_baselines3 import PPO

    from racecav.common.config import TrainConfig
    from racecav.training.imitation_term import make_callback
    from racecav.training.train import make_venv

    tc = TrainConfig(preset="fast", n_steps=8, batch_size=32, n_epochs=1, bc_coef=1.0, bc_grad_steps=3,
                     bc_label_steps=2, bc_learning_rate=1e-3, expert="mirror", mirror_families="left-to-right",
                     init_from=ROW16, env=EnvConfig(n_envs=8, n_obstacles=0, scenarios=str(crossings),
                                                    scenario_share=1.0, obs_stack=2, lidar="wide"))
    venv = make_venv(tc, seed=5)
    cb = make_callback(tmp_path, tc, venv, seed=0)
    model = PPO("MlpPolicy", venv, n_steps=8, batch_size=32, n_epochs=1, device="cpu")
    model.learn(64, callback=cb)
    p = model.policy
    steps = [s["step"].item() for s in p.optimizer.state.values()]
    critic = [t.detach().clone() for t in p.mlp_extractor.value_net.parameters()]
    actor = [t.detach().clone() for t in p.mlp_extractor.policy_net.parameters()]
    cb._fit()
    assert cb.opt is not p.optimizer and cb.opt.param_groups[0]["lr"] == 1e-3
    assert [s["step"].item() for s in p.optimizer.state.values()] == steps
    assert all(torch.equal(a, b) for a, b in zip(critic, p.mlp_extractor.value_net.parameters()))
    assert not all(torch.equal(a, b) for a, b in zip(actor, p.mlp_extractor.policy_net.parameters()))


def test_aux_seen_head_is_fitted_on_the_labelled_steps_and_not_shipped(tmp_path, crossings, capsys):
    """``--aux-seen C`` (with --bc-coef --expert hold): each labelled step also records whether a
    car is in the ego's scan; the held steps (no car seen yet) never are. A training-only head on
    the actor's last layer is fitted to it; the saved policy has the same parameters as without it."""
    from stable_baselines3 import PPO

    from racecav.cli import main
    from racecav.training.imitation_term import make_callback
    from racecav.training.runs import load_run_config
    from racecav.training.train import make_venv

    flags = ["--preset", "fast", "--n-envs", "8", "--n-steps", "8", "--batch-size", "32", "--n-epochs", "1",
             "--checkpoint-every", "64", "--n-obstacles", "0", "--scenarios", str(crossings),
             "--scenario-share", "1.0", "--obs-stack", "2", "--lidar", "wide", "--bc-coef", "1",
             "--bc-grad-steps", "2", "--expert", "hold", "--mirror-families", "left-to-right,right-to-left",
             "--bc-label-steps", "0", "--hold-until-seen", "--anchor-seen", "--init-from", ROW16]
    run = tmp_path / "run"
    assert main(["train", "overtake", "--no-progress", "--run-dir", str(run), "--steps", "64",
                 "--aux-seen", "0.5", *flags]) == 0
    tc = load_run_config(run)[0]
    assert tc.aux_seen == 0.5
    venv = make_venv(tc, seed=5)
    cb = make_callback(tmp_path, tc, venv, seed=0)
    model = PPO("MlpPolicy", venv, n_steps=8, batch_size=32, n_epochs=1, device="cpu")
    keys = set(model.policy.state_dict())
    model.learn(256, callback=cb)
    inview, held = cb.inview[:cb.size], cb.man[:cb.size]
    assert held.any() and not inview[held].any()  # held: nothing in view yet
    assert inview[~held].any()  # after the hold: the car in the scan at some steps
    assert cb.aux_head is not None and set(model.policy.state_dict()) == keys  # not part of the policy
    plain = tmp_path / "plain"
    assert main(["train", "overtake", "--no-progress", "--run-dir", str(plain), "--steps", "64", *flags]) == 0
    a = PPO.load(run / "latest.zip", device="cpu").policy.state_dict()
    b = PPO.load(plain / "latest.zip", device="cpu").policy.state_dict()
    assert set(a) == set(b) and all(a[k].shape == b[k].shape for k in a)
    assert main(["train", "overtake", "--no-progress", "--run-dir", str(tmp_path / "bad"), "--steps", "64",
                 "--scenarios", str(crossings), "--aux-seen", "0.5"]) == 2
    assert "--aux-seen is fitted on --expert hold's labelled steps" in capsys.readouterr().out


@pytest.mark.parametrize("relabel", ["stop", "yield"])
def test_stop_teacher_driven_itself_passes_both_timings_on_both_sides(tmp_path, relabel):
    """--expert stop and yield: driven by its own labels, the teacher passes the paper's crossings
    from either side in both timings (fast world), where a straight ego at full throttle loses the
    conflict-timed ones; stop brakes before every crossing, yield only while a car in its scan is
    busy (so never where none is in view); both steer the road's tracking steer and label only the
    named families short of the crossing; both need the run's brake."""
    from racecav.training.expert import tracking_steer

    folder = tmp_path / "sides"
    folder.mkdir()
    names = ["left-to-right", "conflict-left-to-right", "right-to-left", "conflict-right-to-left"]
    for name in names:
        shutil.copy(SCENARIOS_DIR / f"{name}.toml", folder / f"{name}.toml")
    policy = row31()  # it drives on past the crossing, where the teacher's labels end

    def env_of(brake):
        return FastVecEnv(config=EnvConfig(n_envs=64, scenarios=str(folder), scenario_share=1.0, n_obstacles=0,
                                           lidar="wide", obs_stack=policy.obs_stack, obs_stride=policy.obs_stride,
                                           brake_below=brake), seed=5)

    with pytest.raises(ValueError, match="brake-below"):
        MirrorTeacher(policy, env_of(None), names, relabel=relabel)

    def drive(env, teacher=None, labelled=()):
        (world,) = env.worlds
        env.reset()
        fam0 = np.array(world.scenario_families)[world.scenario_index]
        done, ok, braked = np.zeros(env.num_envs, bool), np.zeros(env.num_envs, bool), np.zeros(env.num_envs, bool)
        while not done.all():
            raw = env._stacked()
            if teacher is None:
                act = np.tile(np.array([1.0, 0.0], np.float32), (env.num_envs, 1))
            else:
                act, mask = teacher.labels(raw)
                fam = np.array(world.scenario_families)[world.scenario_index]
                mine = np.isin(fam, labelled)  # only the labelled families
                assert np.array_equal(mask, mine & (world.x[:, 0] < 0.0))
                assert np.allclose(act[mask, 1], tracking_steer(world)[mask])
                assert np.array_equal(act[~mask], policy(raw)[~mask])  # elsewhere the policy's own action
                brake = mask & (act[:, 0] < -0.5) & ~done
                if relabel == "yield" and brake.any():  # it brakes only for a car its scan shows
                    assert world.seen_by_agent(np.flatnonzero(brake)).any(axis=1).all()
                braked |= brake
            _obs, _r, d, infos = env.step(act.astype(np.float32))
            for i in np.flatnonzero(d & ~done):
                ok[i] = infos[i].get("is_success", False)
            done |= d
        env.close()
        return fam0, ok, braked

    fam, ok, braked = drive(env_of(-0.5), None)
    assert not ok[np.char.startswith(fam.astype(str), "conflict")].any()  # the straight pass loses these
    env = env_of(-0.5)
    fam, ok, braked = drive(env, MirrorTeacher(policy, env, names[:2], relabel=relabel), names[:2])
    left = np.isin(fam, names[:2])
    assert ok[left].all()
    if relabel == "stop":
        assert braked[left].all()  # every labelled world stops, and passes
    else:  # it waits for the synchronised car (and brakes briefly for the paper-timed one once in view)
        assert braked[fam == names[1]].all()
    # the same teacher on the right-hand side: it is side-neutral
    env = env_of(-0.5)
    fam, ok, _braked = drive(env, MirrorTeacher(policy, env, names, relabel=relabel), names)
    assert ok.all(), {f: ok[fam == f].mean() for f in names}


@pytest.mark.parametrize("expert", ["stop", "yield"])
def test_stop_probe_reports_the_teacher_beside_the_straight_car(capsys, expert):
    """`racecav train stop-probe [--expert stop|yield]`: per family, the teacher where it drives, beside
    the non-evading references on the same seeds; a family it does not drive goes straight at full throttle."""
    import re

    from racecav.cli import main

    files = ",".join(str(SCENARIOS_DIR / f"{n}.toml") for n in ("conflict-left-to-right", "left-to-right"))
    assert main(["train", "stop-probe", "--scenarios", files, "--families", "conflict-left-to-right", "--n", "64",
                 "--expert", expert]) == 0
    rows = {m[0]: (int(m[1]), int(m[2]), int(m[3]), int(m[4])) for m in
            re.findall(r"^\| ([\w-]+) \| (\d+) \| (\d+) % \| (\d+) % \| (\d+) % \|$", capsys.readouterr().out, re.M)}
    # columns: the teacher, straight at 1 m/s, straight at full throttle (the references)
    assert rows["conflict-left-to-right"][1:] == (100, 0, 0)  # stops for the synchronised car; no straight car passes
    assert rows["left-to-right"][1:] == (100, 0, 100)  # not driven by the teacher: it is the full-throttle car there
    assert sum(r[0] for r in rows.values()) == 64
    with pytest.raises(SystemExit, match="--families"):
        main(["train", "stop-probe", "--scenarios", files, "--families", "nope", "--n", "8"])


def test_yield_anchor_families_get_the_approach_label_then_keep_their_own_answer(tmp_path):
    """--expert yield --anchor-families F: in F's scenarios, tracking at full throttle until a car
    has been in the ego's scan (short of the crossing), then the policy's own action (anchored),
    latched for the episode; the yield families are never anchored. A teacher trained without a
    brake labels its coasts (a_T < 0) as coasts (0), not as the run's brake."""
    from racecav.training.runs import source_env
    from racecav.training.expert import latch_seen, tracking_steer
    from racecav.training.select import COMMITTED

    folder = tmp_path / "mix"
    folder.mkdir()
    # the head-on car is in view from the start (anchored at once), the crossing one behind a corner
    yielding, anchors = ["conflict-left-to-right", "left-to-right"], ["conflict-right-to-left", "head-to-head"]
    for name in yielding + anchors:
        shutil.copy(SCENARIOS_DIR / f"{name}.toml", folder / f"{name}.toml")
    policy = row31()
    env = FastVecEnv(config=EnvConfig(n_envs=32, scenarios=str(folder), scenario_share=1.0, n_obstacles=0,
                                      lidar="wide", obs_stack=2, brake_below=-0.5), seed=3)
    # row 31 has no brake: its a_T < 0 (a coast) must not become a brake label here
    assert source_env(COMMITTED / "avoid-gsde-flow120" / "checkpoints" / "step_005005312.zip", "brake_below", None) is None
    assert source_env(COMMITTED / "avoid-gsde-stoplook" / "latest.zip", "brake_below", None) == -0.5
    teacher = MirrorTeacher(policy, env, yielding, anchors, relabel="yield", teacher_brakes=False)
    (world,) = env.worlds
    env.reset()
    seen = np.zeros(env.num_envs, bool)
    approach = anchored = coasts = 0
    for _ in range(60):
        raw = env._stacked()
        act, mask = teacher.labels(raw)
        anch = teacher.anchored()
        fam = np.array(world.scenario_families)[world.scenario_index]
        mine = np.isin(fam, anchors)
        seen = latch_seen(world, seen, np.arange(env.num_envs))
        held = mine & ~seen & (world.x[:, 0] < 0.0)
        assert np.array_equal(mask & mine, held)  # the approach, until a car is in view
        assert np.allclose(act[held], np.stack([np.ones(held.sum()), tracking_steer(world)[held]], axis=1))
        assert np.array_equal(anch, mine & ~held)  # after it: anchored, the label is the policy's own
        own = policy(raw)
        coasts += int((own[anch, 0] < 0.0).sum())
        own[:, 0] = np.maximum(own[:, 0], 0.0)
        assert np.array_equal(act[anch], own[anch])
        approach, anchored = approach + held.sum(), anchored + anch.sum()
        env.step(policy(raw))
    assert approach > 0 and anchored > 0 and coasts > 0  # every kind of step was met

    class Coasting:  # another policy without a brake, for --anchor-from
        def __call__(self, obs):
            return np.tile(np.array([-0.8, 0.2], np.float32), (len(obs), 1))

    teacher.set_anchor_policy(Coasting(), teacher_brakes=False)
    for _ in range(30):
        raw = env._stacked()
        act, mask = teacher.labels(raw)
        anch = teacher.anchored()
        assert anch.any() and np.allclose(act[anch], [0.0, 0.2])  # its action, its coast kept a coast
        assert np.array_equal(act[~anch & ~mask], policy(raw)[~anch & ~mask])
        env.step(policy(raw))
    env.close()


def test_anchor_from_is_refused_without_anchors_or_file(tmp_path, capsys):
    from racecav.cli import main

    base = ["train", "overtake", "--preset", "fast", "--run-dir", str(tmp_path / "r"), "--steps", "1000"]
    assert main(base + ["--anchor-from", str(tmp_path / "x.zip")]) == 2
    assert "--anchor-families" in capsys.readouterr().out
    assert main(base + ["--anchor-from", str(tmp_path / "x.zip"), "--bc-coef", "0.1", "--anchor-families", "head-on"]) == 2
    assert "no such file" in capsys.readouterr().out


def test_yield_family_also_anchored_waits_until_its_car_has_stopped(tmp_path):
    """--expert yield with a family in both --mirror-families and --anchor-families (braking): the
    yield labels until a car in the ego's scan near the crossing has stopped, then the policy's own
    action for the rest of the episode; a family only in --mirror-families is never released."""
    from racecav.evaluation import suite as S
    from racecav.training.mirror import APPROACH_M, STOPPED_V

    ff = S.load_families("conflicts")
    ff = ff.model_copy(update={"families": [f for f in ff.families if f.name in ("braking", "cross-left")]})
    S.generate(ff, tmp_path / "suite", n_test=2, n_train=16, seed=5, progress=False)
    policy = row31()
    env = FastVecEnv(config=EnvConfig(n_envs=32, scenarios=str(tmp_path / "suite"), scenario_share=1.0,
                                      n_obstacles=0, lidar="wide", obs_stack=2, brake_below=-0.5), seed=4)
    teacher = MirrorTeacher(policy, env, ["braking", "cross-left"], ["braking"], relabel="yield",
                            teacher_brakes=False)
    (world,) = env.worlds
    env.reset()
    stopped = np.zeros(env.num_envs, bool)  # the release, latched here as the docstring says
    released = braked = 0
    for _ in range(120):
        stopped[world.time < 1e-9] = False
        raw = env._stacked()
        act, mask = teacher.labels(raw)
        anch = teacher.anchored()
        fam = np.array([f.split("/")[-1] for f in world.scenario_families])[world.scenario_index]
        d = np.hypot(world.x[:, 1:], world.y[:, 1:] - world.start_pose[:, 1:2])
        now = ((d < APPROACH_M) & (world.v[:, 1:] < STOPPED_V) & world.seen_by_agent(np.arange(env.num_envs))).any(axis=1)
        short = world.x[:, 0] < 0.0
        stopped |= now & short & (fam == "braking")
        brk = (fam == "braking") & short
        assert np.array_equal(anch[brk], stopped[brk])  # anchored exactly from the stop on
        assert not (mask & anch).any() and not anch[fam == "cross-left"].any()
        own = policy(raw)
        own[:, 0] = np.maximum(own[:, 0], 0.0)
        assert np.array_equal(act[anch], own[anch])
        released += int((anch & brk).sum())
        braked += int((mask & brk & (act[:, 0] < 0)).sum())
        env.step(act)
    assert released > 0 and braked > 0  # both halves of the family's label were met
    env.close()


def test_yield_follows_a_car_that_turned_in_ahead_and_waits_for_an_oncoming_one_only_where_it_turns(tmp_path, monkeypatch):
    """--expert yield on the turning family, driven by its own labels: the car that turns into the
    ego's lane ahead (right_into) is followed (the label is never above the gap's speed, wherever
    the ego is) and the oncoming car that turns across (left_across) is waited for only near the
    crossing; both variants pass, where the straight car at full throttle does not. Without the
    follow the turned-in car is rear-ended; with the oncoming car busy from APPROACH_M out the ego
    waits for it to crawl up (synchronised to the stopped ego) and the episode ends first."""
    from racecav.evaluation import suite as S
    from racecav.training import mirror as M
    from racecav.training.select import ConstantAction

    ff = S.load_families("conflicts")
    ff = ff.model_copy(update={"families": [f for f in ff.families if f.name == "turning"]})
    S.generate(ff, tmp_path / "suite", n_test=2, n_train=40, seed=6, progress=False)

    def drive(teacher_on: bool) -> tuple[np.ndarray, np.ndarray]:
        env = FastVecEnv(config=EnvConfig(n_envs=64, scenarios=str(tmp_path / "suite"), scenario_share=1.0,
                                          n_obstacles=0, lidar="wide", obs_stack=2, brake_below=-0.5), seed=3)
        teacher = MirrorTeacher(ConstantAction(1.0), env, ["turning"], relabel="yield") if teacher_on else None
        (world,) = env.worlds
        env.reset()
        into = np.array([abs(world.scenarios[k].obstacles[0].yaw_deg - 90.0) < 1.0 for k in world.scenario_index])
        done, ok = np.zeros(env.num_envs, bool), np.zeros(env.num_envs, bool)
        while not done.all():
            if teacher is None:
                act = np.tile(np.array([1.0, 0.0], np.float32), (env.num_envs, 1))
            else:
                act, mask = teacher.labels(env._stacked())
                # labelled past the crossing: only to follow, or to hold its side round an oncoming car
                past = mask & (world.x[:, 0] >= 0.0) & ~done & ~teacher.steered()
                if past.any():
                    following, t_follow = M.MirrorTeacher._follow(world, np.flatnonzero(past))
                    assert following.all() and np.allclose(act[past, 0], t_follow)
            _obs, _r, d, infos = env.step(act.astype(np.float32))
            for i in np.flatnonzero(d & ~done):
                ok[i] = infos[i].get("is_success", False)
            done |= d
        env.close()
        return into, ok

    into, ok = drive(True)
    assert into.sum() >= 16 and (~into).sum() >= 16  # both variants drawn
    # left_across: its car may first look like an oncoming one to steer round (MirrorTeacher._dodge)
    assert ok[into].mean() >= 0.7 and ok[~into].mean() >= 0.6, (ok[into].mean(), ok[~into].mean())
    _into, straight = drive(False)
    assert straight.mean() <= 0.1  # a benchmark: the straight car at full throttle loses it

    monkeypatch.setattr(M.MirrorTeacher, "_follow", staticmethod(lambda w, look: (np.zeros(len(look), bool),
                                                                                  np.ones(len(look)))))
    into, ok = drive(True)
    assert ok[into].mean() <= 0.3  # rear-ended without the follow
    monkeypatch.undo()
    monkeypatch.setattr(M, "ONCOMING_M", M.APPROACH_M)
    into, ok = drive(True)
    assert ok[~into].mean() <= 0.3, ok[~into].mean()  # waits too long for the oncoming car


def test_anchor_policy_sees_its_own_stride_from_the_envs_history(tmp_path):
    """--anchor-from a policy trained on consecutive scans, in a run with a longer --obs-stride: its
    anchored labels are its actions on its own view (the env's history, scans 1 period apart), not
    on the run's; a view older than the history is refused."""
    from racecav.training.select import COMMITTED, checkpoint_policy

    folder = tmp_path / "mix"
    folder.mkdir()
    yielding, anchors = ["conflict-left-to-right"], ["head-to-head"]
    for name in yielding + anchors:
        shutil.copy(SCENARIOS_DIR / f"{name}.toml", folder / f"{name}.toml")
    anchor = checkpoint_policy(COMMITTED / "avoid-gsde-flow120" / "checkpoints" / "step_005005312.zip")
    assert (anchor.obs_stack, anchor.obs_stride) == (2, 1)
    env = FastVecEnv(config=EnvConfig(n_envs=16, scenarios=str(folder), scenario_share=1.0, n_obstacles=0,
                                      lidar="wide", obs_stack=2, obs_stride=4, brake_below=-0.5), seed=3)
    teacher = MirrorTeacher(anchor, env, yielding, anchors, relabel="yield", teacher_brakes=False)
    teacher.set_anchor_policy(anchor, teacher_brakes=False)
    env.reset()
    differs = checked = 0
    for _ in range(40):
        raw = env._stacked()
        own_view = env.stacked_view(2, 1)
        assert np.array_equal(own_view[:, :raw.shape[1] // 2], raw[:, :raw.shape[1] // 2])  # the newest scan
        act, mask = teacher.labels(raw)
        anch = teacher.anchored()
        want = anchor(own_view)
        want[:, 0] = np.maximum(want[:, 0], 0.0)
        assert np.allclose(act[anch], want[anch], atol=1e-5)  # (a batch of another size: float rounding)
        checked += int(anch.sum())
        differs += int((np.abs(anchor(raw)[anch] - anchor(own_view)[anch]) > 1e-3).any(axis=1).sum())
        env.step(act)
    assert checked > 0 and differs > 0  # the two views give other actions: the test can tell them apart
    with pytest.raises(ValueError, match="history"):
        env.stacked_view(3, 4)
    env.close()


def test_yield_steers_round_an_oncoming_or_stopped_car_and_does_not_wait_for_it(tmp_path, monkeypatch):
    """--expert yield on the head-on, stopped and braking families, driven by its own labels
    (`racecav train stop-probe`): it steers round a car that blocks its path (oncoming or stopped)
    and passes where the straight cars do not; without the steer round (monkeypatched away) it
    meets the oncoming car and waits for ever behind the stopped one."""
    from racecav.evaluation import suite as S
    from racecav.training import mirror as M
    from racecav.training.select import ConstantAction
    from racecav.training.stop_probe import stop_probe

    ff = S.load_families("conflicts")
    names = ["head-on", "stopped", "braking"]
    ff = ff.model_copy(update={"families": [f for f in ff.families if f.name in names]})
    S.generate(ff, tmp_path / "suite", n_test=2, n_train=40, seed=8, progress=False)
    res = stop_probe(str(tmp_path / "suite"), names, 96, seed=2, relabel="yield")
    teacher, slow, fast = (res[k] for k in ("yield", "straight 1 m/s", "straight, full throttle"))
    for fam, (k, ok) in teacher.items():
        assert k >= 20 and ok >= 0.8, (fam, k, ok)
        assert slow[fam][1] <= 0.1 and fast[fam][1] <= 0.1  # a benchmark: the straight cars lose it
    # the steps it steers round a car are labelled ones, with a steer of their own (--bc-balance's half)
    from racecav.training.expert import tracking_steer

    env = FastVecEnv(config=EnvConfig(n_envs=64, scenarios=str(tmp_path / "suite"), scenario_share=1.0,
                                      n_obstacles=0, lidar="wide", obs_stack=1, brake_below=-0.5), seed=2)
    t = M.MirrorTeacher(ConstantAction(1.0), env, names, relabel="yield")
    env.reset()
    steered = 0
    for _ in range(60):
        act, mask = t.labels(env._stacked())
        st = t.steered()
        assert not (st & ~mask).any()
        track = np.concatenate([tracking_steer(w) for w in env.worlds])
        steered += int(st.sum())
        assert (np.abs(act[st, 1] - track[st]) > 1e-6).mean() > 0.5 if st.any() else True
        env.step(act.astype(np.float32))
    env.close()
    assert 0 < steered
    monkeypatch.setattr(M.MirrorTeacher, "_dodge", staticmethod(lambda w, look, holding: (np.zeros(len(look), bool),
                                                                                           np.zeros(len(look)))))
    without = stop_probe(str(tmp_path / "suite"), names, 96, seed=2, relabel="yield")["yield"]
    assert without["suite/head-on"][1] <= 0.1 and without["suite/stopped"][1] <= 0.1, without
    monkeypatch.undo()

    # a car dead ahead (the paper's head-to-head, offset 0 +- 5 cm) is passed on its right, every time
    env = FastVecEnv(config=EnvConfig(n_envs=32, scenarios=str(SCENARIOS_DIR / "head-to-head.toml"), scenario_share=1.0,
                                      n_obstacles=0, lidar="wide", obs_stack=1, brake_below=-0.5), seed=2)
    t = M.MirrorTeacher(ConstantAction(1.0), env, ["head-to-head"], relabel="yield")
    env.reset()
    first = np.full(env.num_envs, np.nan)
    for _ in range(60):
        act, _mask = t.labels(env._stacked())
        new = t.steered() & np.isnan(first)
        first[new] = act[new, 1]
        env.step(act.astype(np.float32))
    env.close()
    assert not np.isnan(first).any() and (first < 0).all(), first  # steer < 0: to the right
    assert without["suite/braking"][1] <= teacher["suite/braking"][1] - 0.3, without  # some stop off the path


def test_yield_holds_its_side_round_an_oncoming_car_until_it_is_past(monkeypatch):
    """--expert yield on the conflict-timed head-to-head, driven by its own labels: once it steers
    round the oncoming car it keeps full throttle until the car is past. Without the hold
    (DODGE_HOLD_M taking the band back to the path's width) the car stops blocking once the ego is
    half out of its way, and the label flips to braking mid-manoeuvre (the flip a policy fitted to
    these labels learnt as steering back and forth)."""
    from racecav.training import mirror as M
    from racecav.training.expert import tracking_steer
    from racecav.training.select import ConstantAction

    def braked_while_passing():
        env = FastVecEnv(config=EnvConfig(n_envs=32, scenarios=str(SCENARIOS_DIR / "conflict-head-to-head.toml"),
                                          scenario_share=1.0, n_obstacles=0, lidar="wide", obs_stack=1,
                                          brake_below=-0.5), seed=2)
        t = M.MirrorTeacher(ConstantAction(1.0), env, ["conflict-head-to-head"], relabel="yield")
        env.reset()
        w = env.worlds[0]
        started, braked, done = (np.zeros(env.num_envs, bool) for _ in range(3))
        for _ in range(80):
            act, mask = t.labels(env._stacked())
            free = t.in_families() & ~mask
            act[free, 1] = tracking_steer(w)[free]
            started |= t.steered() & ~done
            braked |= started & ~done & (w.x[:, 0] < w.x[:, 1]) & (act[:, 0] < 0)
            done |= env.step(act.astype(np.float32))[2]
        env.close()
        return started, braked

    started, braked = braked_while_passing()
    assert started.all() and not braked.any(), (started.mean(), braked.mean())
    monkeypatch.setattr(M, "DODGE_HOLD_M", 0.1 - M.DODGE_CLEAR_M)
    started, braked = braked_while_passing()
    assert started.all() and braked.mean() > 0.5, braked.mean()
