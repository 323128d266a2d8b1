"""The yield teacher of ``racecav train dagger`` (training/teacher.py), driven by its own labels."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from racecav.common.config import EnvConfig
from racecav.common.scenario import SCENARIOS_DIR
from racecav.evaluation.inprocess import ConstantAction, reference_drivers
from racecav.training import teacher as M
from racecav.training.teacher import YieldTeacher, tracking_steer
from racecav.training.vec_env import FastVecEnv
from tests.checkpoints_support import ROW31


def row31():
    """Row 31 at 5 M (the avoid shipped until 2026-12-05; two consecutive wide scans, no brake): the
    frozen policy these teacher tests relabel, whose behaviour they were written against."""
    from racecav.training.policy_io import checkpoint_policy

    return checkpoint_policy(ROW31)


def drive_teacher(scenarios: str, families: list[str], n: int, seed: int) -> dict[str, dict[str, tuple[int, float]]]:
    """{driver: {family: (episodes, success)}}: the yield teacher driven by its own labels (on along
    the road where it gives none), then the non-evading references, on the same seeds."""
    cfg = EnvConfig(scenarios=scenarios, scenario_share=1.0, lidar="wide", obs_stack=1, brake_below=-0.5)
    out = {}
    for name, driver in {"yield": None, **reference_drivers()}.items():
        env = FastVecEnv(n_envs=n, config=cfg, seed=seed)
        obs = env.reset()
        teacher = YieldTeacher(ConstantAction(1.0), env, families) if driver is None else None
        fam = np.concatenate([np.array(w.scenario_families)[w.scenario_index] for w in env.worlds])
        done, ok = np.zeros(n, bool), np.zeros(n, bool)
        while not done.all():
            if teacher:
                act, mask = teacher.labels(obs)
                free = teacher.in_families() & ~mask
                if free.any():
                    act[free, 1] = np.concatenate([tracking_steer(w) for w in env.worlds])[free]
            else:
                act = driver(obs)
            obs, _r, d, infos = env.step(act.astype(np.float32))
            for i in np.flatnonzero(d & ~done):
                ok[i] = infos[i].get("is_success", False)
            done |= d
        env.close()
        out[name] = {f: (int((fam == f).sum()), float(ok[fam == f].mean())) for f in sorted(set(fam.tolist()))}
    return out


def test_teacher_names_a_family_the_scenarios_lack_and_needs_the_brake(tmp_path):
    folder = tmp_path / "scenarios"
    folder.mkdir()
    for name in ("left-to-right", "right-to-left"):
        shutil.copy(SCENARIOS_DIR / f"{name}.toml", folder / f"{name}.toml")

    def env_of(brake):
        return FastVecEnv(config=EnvConfig(n_envs=4, scenarios=str(folder), scenario_share=1.0, n_obstacles=0,
                                           lidar="wide", obs_stack=2, brake_below=brake), seed=0)

    with pytest.raises(ValueError, match=r"cross-left.*left-to-right', 'right-to-left"):
        YieldTeacher(row31(), env_of(-0.5), ["cross-left"])
    with pytest.raises(ValueError, match="brake-below"):
        YieldTeacher(row31(), env_of(None), ["left-to-right"])


def test_yield_teacher_driven_itself_passes_both_timings_on_both_sides(tmp_path):
    """Driven by its own labels, the teacher passes the paper's crossings from either side in both
    timings (fast world), where a straight ego at full throttle loses the conflict-timed ones; it
    brakes only while a car in its scan is busy (so never where none is in view), steers the road's
    tracking steer and labels only the named families short of the crossing."""
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
                if brake.any():  # it brakes only for a car its scan shows
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
    fam, ok, braked = drive(env, YieldTeacher(policy, env, names[:2]), names[:2])
    left = np.isin(fam, names[:2])
    assert ok[left].all()
    # it waits for the synchronised car (and brakes briefly for the paper-timed one once in view)
    assert braked[fam == names[1]].all()
    # the same teacher on the right-hand side: it is side-neutral
    env = env_of(-0.5)
    fam, ok, _braked = drive(env, YieldTeacher(policy, env, names), names)
    assert ok.all(), {f: ok[fam == f].mean() for f in names}


def test_yield_follows_a_car_that_turned_in_ahead_and_waits_for_an_oncoming_one_only_where_it_turns(tmp_path, monkeypatch):
    """--expert yield on the turning family, driven by its own labels: the car that turns into the
    ego's lane ahead (right_into) is followed (the label is never above the gap's speed, wherever
    the ego is) and the oncoming car that turns across (left_across) is waited for only near the
    crossing; both variants pass, where the straight car at full throttle does not. Without the
    follow the turned-in car is rear-ended; with the oncoming car busy from APPROACH_M out the ego
    waits for it to crawl up (synchronised to the stopped ego) and the episode ends first."""
    from racecav.evaluation import suite as S

    ff = S.load_families("conflicts")
    ff = ff.model_copy(update={"families": [f for f in ff.families if f.name == "turning"]})
    S.generate(ff, tmp_path / "suite", n_test=2, n_train=40, seed=6, progress=False)

    def drive(teacher_on: bool) -> tuple[np.ndarray, np.ndarray]:
        env = FastVecEnv(config=EnvConfig(n_envs=64, scenarios=str(tmp_path / "suite"), scenario_share=1.0,
                                          n_obstacles=0, lidar="wide", obs_stack=2, brake_below=-0.5), seed=3)
        teacher = YieldTeacher(ConstantAction(1.0), env, ["turning"]) if teacher_on else None
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
                    following, t_follow = M.YieldTeacher._follow(world, np.flatnonzero(past))
                    assert following.all() and np.allclose(act[past, 0], t_follow)
            _obs, _r, d, infos = env.step(act.astype(np.float32))
            for i in np.flatnonzero(d & ~done):
                ok[i] = infos[i].get("is_success", False)
            done |= d
        env.close()
        return into, ok

    into, ok = drive(True)
    assert into.sum() >= 16 and (~into).sum() >= 16  # both variants drawn
    # left_across: its car may first look like an oncoming one to steer round (YieldTeacher._dodge)
    assert ok[into].mean() >= 0.7 and ok[~into].mean() >= 0.6, (ok[into].mean(), ok[~into].mean())
    _into, straight = drive(False)
    assert straight.mean() <= 0.1  # a benchmark: the straight car at full throttle loses it

    monkeypatch.setattr(M.YieldTeacher, "_follow", staticmethod(lambda w, look: (np.zeros(len(look), bool),
                                                                                  np.ones(len(look)))))
    into, ok = drive(True)
    assert ok[into].mean() <= 0.3  # rear-ended without the follow
    monkeypatch.undo()
    monkeypatch.setattr(M, "ONCOMING_M", M.APPROACH_M)
    into, ok = drive(True)
    assert ok[~into].mean() <= 0.3, ok[~into].mean()  # waits too long for the oncoming car


def test_yield_steers_round_an_oncoming_or_stopped_car_and_does_not_wait_for_it(tmp_path, monkeypatch):
    """--expert yield on the head-on, stopped and braking families, driven by its own labels
    (drive_teacher): it steers round a car that blocks its path (oncoming or stopped)
    and passes where the straight cars do not; without the steer round (monkeypatched away) it
    meets the oncoming car and waits for ever behind the stopped one."""
    from racecav.evaluation import suite as S

    ff = S.load_families("conflicts")
    names = ["head-on", "stopped", "braking"]
    ff = ff.model_copy(update={"families": [f for f in ff.families if f.name in names]})
    S.generate(ff, tmp_path / "suite", n_test=2, n_train=40, seed=8, progress=False)
    res = drive_teacher(str(tmp_path / "suite"), names, 96, seed=2)
    teacher, slow, fast = (res[k] for k in ("yield", "straight 1 m/s", "straight, full throttle"))
    for fam, (k, ok) in teacher.items():
        assert k >= 20 and ok >= 0.8, (fam, k, ok)
        assert slow[fam][1] <= 0.1 and fast[fam][1] <= 0.1  # a benchmark: the straight cars lose it
    # the steps it steers round a car are labelled ones, with a steer of their own (--bc-balance's half)
    env = FastVecEnv(config=EnvConfig(n_envs=64, scenarios=str(tmp_path / "suite"), scenario_share=1.0,
                                      n_obstacles=0, lidar="wide", obs_stack=1, brake_below=-0.5), seed=2)
    t = M.YieldTeacher(ConstantAction(1.0), env, names)
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
    monkeypatch.setattr(M.YieldTeacher, "_dodge", staticmethod(lambda w, look, holding: (np.zeros(len(look), bool),
                                                                                           np.zeros(len(look)))))
    without = drive_teacher(str(tmp_path / "suite"), names, 96, seed=2)["yield"]
    assert without["suite/head-on"][1] <= 0.1 and without["suite/stopped"][1] <= 0.1, without
    monkeypatch.undo()

    # a car dead ahead (the paper's head-to-head, offset 0 +- 5 cm) is passed on its right, every time
    env = FastVecEnv(config=EnvConfig(n_envs=32, scenarios=str(SCENARIOS_DIR / "head-to-head.toml"), scenario_share=1.0,
                                      n_obstacles=0, lidar="wide", obs_stack=1, brake_below=-0.5), seed=2)
    t = M.YieldTeacher(ConstantAction(1.0), env, ["head-to-head"])
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
    def braked_while_passing():
        env = FastVecEnv(config=EnvConfig(n_envs=32, scenarios=str(SCENARIOS_DIR / "conflict-head-to-head.toml"),
                                          scenario_share=1.0, n_obstacles=0, lidar="wide", obs_stack=1,
                                          brake_below=-0.5), seed=2)
        t = M.YieldTeacher(ConstantAction(1.0), env, ["conflict-head-to-head"])
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
