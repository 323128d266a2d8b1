"""The gymnasium env racecav/Overtake-v0 and the fast batched world: spaces, reward, termination,
auto-reset, determinism, lidar geometry, and a short PPO run."""

import math

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import racecav.training  # noqa: F401  (registers racecav/Overtake-v0)
from racecav.common.lidar import published_scan, ray_angles
from racecav.common.vehicle import load_car
from racecav.sim.fast_world import FastWorld
from racecav.training.env import OvertakeEnv, reward
from racecav.training.vec_env import FastVecEnv


# --------------------------------------------------------------------------- env API
def test_env_checker_fast():
    env = gym.make("racecav/Overtake-v0", backend="fast")
    check_env(env.unwrapped)
    assert env.observation_space.shape == (170,)
    assert env.action_space.shape == (2,)
    assert np.all(env.action_space.low == -1) and np.all(env.action_space.high == 1)


def test_env_checker_bullet():
    env = gym.make("racecav/Overtake-v0", backend="bullet", n_obstacles=15)
    try:
        check_env(env.unwrapped)
        obs, _ = env.reset(seed=3)
        assert obs.shape == (170,) and obs.dtype == np.float32
    finally:
        env.close()


def test_options_are_validated():
    with pytest.raises(ValueError, match="heading"):
        OvertakeEnv(heading="sideways")
    with pytest.raises(ValueError, match="n_obstacles"):
        OvertakeEnv(n_obstacles=16)
    with pytest.raises(ValueError, match="control_period_s"):
        OvertakeEnv(control_period=-0.1)
    with pytest.raises(ValueError, match="backend"):
        OvertakeEnv(backend="mujoco")


def test_brake_action_option():
    """brake_below: a_T below it brakes (both env classes); the paper's action only coasts."""
    with pytest.raises(ValueError, match="brake_below"):
        OvertakeEnv(brake_below=0.5)
    ends = []
    for bb in (None, -0.5):
        env = FastVecEnv(n_envs=2, n_obstacles=0, brake_below=bb, seed=0)
        env.reset()
        for _ in range(15):
            env.step(np.tile([1.0, 0.0], (2, 1)))
        for _ in range(5):
            env.step(np.tile([-1.0, 0.0], (2, 1)))
        ends.append(env.world.agent_state()[:, 3])
    assert ends[0].max() > 0.8 and np.all(ends[1] < 0.2), ends  # coasting keeps most of its speed
    env = OvertakeEnv(backend="fast", n_obstacles=0, brake_below=-0.5)
    env.reset(seed=1)
    for _ in range(15):
        env.step(np.array([1.0, 0.0]))
    for _ in range(5):
        _obs, r, *_ = env.step(np.array([-0.8, 0.0]))
    assert env.world.agent_state()[0, 3] < 0.2 and r == 0.0


# --------------------------------------------------------------------------- reward
def test_reward_cases():
    # 5 T^2 with T = clip(a_T, 0, 1)
    assert reward([0.5], [0.0], [0.0])[0] == pytest.approx(1.25)
    assert reward([1.0], [0.3], [-0.2])[0] == pytest.approx(5.0)
    assert reward([0.0], [0.0], [0.0])[0] == 0.0
    # full-lock reversal on the clipped steering, either way
    assert reward([1.0], [1.0], [-1.0])[0] == -2.0
    assert reward([0.7], [-1.0], [1.0])[0] == -2.0
    # anything short of a full reversal is not penalised
    assert reward([1.0], [0.99], [-1.0])[0] == pytest.approx(5.0)
    assert reward([1.0], [1.0], [1.0])[0] == pytest.approx(5.0)


def test_env_reward_clips_actions():
    env = OvertakeEnv(n_obstacles=0)
    env.reset(seed=0)
    # throttle beyond the box is clipped to 1 (and negative throttle to 0)
    _, r, *_ = env.step(np.array([3.0, 0.0], np.float32))
    assert r == pytest.approx(5.0)
    _, r, *_ = env.step(np.array([-0.5, 0.0], np.float32))
    assert r == 0.0
    # steering beyond [-1, 1] is clipped before the reversal test: 2.5 then -4 is a reversal
    env.step(np.array([0.0, 2.5], np.float32))
    _, r, *_ = env.step(np.array([1.0, -4.0], np.float32))
    assert r == -2.0
    # the first step of an episode has no previous steering
    env.reset(seed=1)
    _, r, *_ = env.step(np.array([1.0, -1.0], np.float32))
    assert r == pytest.approx(5.0)


# --------------------------------------------------------------------------- termination
def _straight_pose(fw_or_env):
    """A pose on the main straight (x in [0, 22], y = 0 is the centreline, lane 2.4 m)."""
    return dict(x=6.0, y=0.0, yaw=0.0)


def test_contact_with_wall_terminates():
    env = OvertakeEnv(n_obstacles=0)
    env.reset(seed=0)
    # on the straight, facing the left wall (y = +1.2) 0.6 m away: full throttle hits it
    env.world.set_state(0, 0, x=6.0, y=0.0, yaw=math.pi / 2, v=0.0, w=0.0, delta=0.0)
    for k in range(30):
        _, r, term, trunc, info = env.step(np.array([1.0, 0.0], np.float32))
        if term:
            break
    assert term and not trunc and info["contact_wall"]
    assert k < 15
    assert info["y"] < 1.2


def test_contact_with_car_terminates():
    env = OvertakeEnv(n_obstacles=1)
    env.reset(seed=0)
    fw = env.world
    fw.set_state(0, 0, x=4.0, y=0.0, yaw=0.0, v=0.0, w=0.0, delta=0.0)
    fw.set_state(0, 1, x=6.0, y=0.0, yaw=0.0, v=0.0, w=0.0, delta=0.0)
    fw.driver = lambda world: np.zeros((1, 1, 2))  # the obstacle stays parked
    # the parked car is seen straight ahead at 2 m - 0.275 (its rear) - 0.20 (mount)
    obs = fw.agent_obs()[0]
    assert obs[84] == pytest.approx(2.0 - fw.car.length / 2 - fw.car.lidar_mount.x, abs=1e-3)
    for _ in range(30):
        _, _, term, trunc, info = env.step(np.array([1.0, 0.0], np.float32))
        if term:
            break
    assert term and info["contact_car"] == 1 and not info["contact_wall"]


def test_vecenv_auto_reset_and_infos():
    venv = FastVecEnv(n_envs=4, n_obstacles=0, time_limit=2.0, seed=0)
    obs = venv.reset()
    w = venv.world
    # env 0 drives into the wall, the others stand still until the 2 s time limit
    w.set_state(0, 0, x=6.0, y=0.0, yaw=math.pi / 2, v=0.0, w=0.0, delta=0.0)
    acts = np.zeros((4, 2))
    acts[0, 0] = 1.0
    ended = {}
    for k in range(20):
        obs, rew, dones, infos = venv.step(acts)
        assert rew.dtype == np.float32 and dones.dtype == bool
        for i in np.flatnonzero(dones):
            ended.setdefault(i, (k, infos[i]))
    k0, info0 = ended[0]
    assert k0 < 19 and info0["TimeLimit.truncated"] is False
    assert info0["terminal_observation"].shape == (170,)
    for i in (1, 2, 3):
        k, info = ended[i]
        assert k == 19 and info["TimeLimit.truncated"] is True
    # after an auto-reset the episode counter restarts
    assert venv.steps[0] == 19 - k0 and np.all(venv.steps[1:] == 0)


# --------------------------------------------------------------------------- determinism
def _rollout(seed, n=40):
    venv = FastVecEnv(n_envs=8, seed=seed)
    out = [venv.reset()]
    rng = np.random.default_rng(1)
    for _ in range(n):
        a = rng.uniform(-1, 1, (8, 2))
        o, r, d, _ = venv.step(a)
        out += [o, r[:, None], d[:, None]]
    return out, venv.world.agent_state()


def test_determinism_under_seed():
    a, sa = _rollout(7)
    b, sb = _rollout(7)
    c, _ = _rollout(8)
    assert all(np.array_equal(x, y) for x, y in zip(a, b)) and np.array_equal(sa, sb)
    assert not np.array_equal(a[0], c[0])


def test_single_env_determinism():
    def run(seed):
        env = gym.make("racecav/Overtake-v0", heading="reversed")
        obs, _ = env.reset(seed=seed)
        seq = [obs]
        for _ in range(20):
            seq.append(env.step(np.array([0.8, 0.1], np.float32))[0])
        return np.array(seq)

    assert np.array_equal(run(3), run(3))
    assert not np.array_equal(run(3), run(4))


# --------------------------------------------------------------------------- world
def _brute_force_scan(fw, n, c):
    """Independent reference: every ray against every edge of every wall box and car box."""
    segs = []

    def box(cx, cy, yaw, hx, hy):
        co, si = math.cos(yaw), math.sin(yaw)
        p = np.array([(cx + co * x - si * y, cy + si * x + co * y)
                      for x, y in ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))])
        segs.append(np.concatenate([p, np.roll(p, -1, 0)], 1))

    r = fw.world.wall_thickness / 2
    for x0, y0, x1, y1 in fw.walls:
        box((x0 + x1) / 2, (y0 + y1) / 2, math.atan2(y1 - y0, x1 - x0), math.hypot(x1 - x0, y1 - y0) / 2 + r, r)
    for j in range(fw.n_cars):
        if j != c and fw.active[n, j]:
            box(fw.x[n, j], fw.y[n, j], fw.yaw[n, j], fw.car.length / 2, fw.car.width / 2)
    S = np.concatenate(segs)
    m = fw.car.lidar_mount
    yaw = fw.yaw[n, c]
    sx = fw.x[n, c] + math.cos(yaw) * m.x - math.sin(yaw) * m.y
    sy = fw.y[n, c] + math.sin(yaw) * m.x + math.cos(yaw) * m.y
    ang = ray_angles(fw.spec).astype(np.float64) + yaw + m.yaw
    d = np.stack([np.cos(ang), np.sin(ang)], 1)[:, None, :]
    a = S[None, :, :2] - [sx, sy]
    e = S[None, :, 2:] - S[None, :, :2]
    den = d[..., 0] * e[..., 1] - d[..., 1] * e[..., 0]
    with np.errstate(all="ignore"):
        t = (a[..., 0] * e[..., 1] - a[..., 1] * e[..., 0]) / den
        u = (a[..., 0] * d[..., 1] - a[..., 1] * d[..., 0]) / den
    t = np.where((t > 0) & (u >= 0) & (u <= 1), t, np.inf).min(1)
    return np.where(t <= fw.spec.range_max, t, np.inf)


@pytest.mark.parametrize("scan", ["paper", "wide"])
def test_lidar_matches_brute_force_for_every_car(scan):
    # the wide scan's outer rays are nearly parallel to the car's side: the fan culling's
    # half-plane test is valid up to +-90 deg
    car = load_car().model_copy(update={"lidar": published_scan(load_car().lidar, scan)})
    fw = FastWorld(n_envs=6, obstacle_lidar=True, seed=0, car=car)
    fw.reset()
    rng = np.random.default_rng(0)
    for _ in range(25):
        _, _, col, _ = fw.step(np.stack([rng.uniform(0, 1, 6), rng.uniform(-1, 1, 6)], 1))
    checked = 0
    for n in range(6):
        for c in range(fw.n_cars):
            if fw.wall_hit[n, c] or fw.car_hit[n, c] >= 0:
                continue  # a car in contact may have its sensor inside a box: one-sided faces
            checked += 1
            ref = _brute_force_scan(fw, n, c)
            got = fw.ranges[n, c]
            assert np.array_equal(np.isfinite(ref), np.isfinite(got))
            fin = np.isfinite(ref)
            assert np.abs(ref[fin] - got[fin]).max() < 1e-4
    assert checked >= 80


def test_agent_is_faster_and_heading_reversed():
    fw = FastWorld(n_envs=2, heading="reversed", seed=0)
    fw.reset()
    # reversed: the agent faces against the centerline direction
    k = fw.cl_idx[:, 0]
    diff = np.angle(np.exp(1j * (fw.yaw[:, 0] - fw.cl[k, 2])))
    assert np.all(np.abs(diff) > math.pi - 0.2)
    assert fw.speed_scale[0, 0] == fw.car.agent_speed_scale > 1.0
    assert np.all(fw.speed_scale[:, 1:] == 1.0)


def test_obstacle_cars_lap_the_track():
    fw = FastWorld(n_envs=2, seed=0)
    fw.reset()
    fw.remove_car(0, 0)
    fw.remove_car(1, 0)
    s0 = fw.cl_idx[:, 1:].copy()
    travelled = np.zeros_like(s0, dtype=float)
    for _ in range(100):
        prev = fw.cl_idx[:, 1:].copy()
        fw.step(np.zeros((2, 2)))
        step = (fw.cl_idx[:, 1:] - prev) % len(fw.cl)
        travelled += np.where(step < len(fw.cl) / 2, step, step - len(fw.cl)) * fw.cl_ds
    # 10 s of traffic: every obstacle car moved forward along the track, few respawns
    assert np.all(travelled[fw.active[:, 1:]] > 5.0)
    assert fw.respawns <= 4
    del s0


def test_figure8_traffic_keeps_to_its_arm_through_the_crossing():
    """On a figure eight the cars' centerline stations come from a local search, so a car
    crossing the junction keeps its own arm (a global nearest point would jump to the other)."""
    fw = FastWorld(n_envs=4, world="figure8", seed=1)
    fw.reset()
    for n in range(4):
        fw.remove_car(n, 0)
    K = len(fw.cl)
    for _ in range(150):  # 15 s: every car passes the crossing at least once
        prev, respawns = fw.cl_idx[:, 1:].copy(), fw.respawns
        fw.step(np.zeros((4, 2)))
        step = (fw.cl_idx[:, 1:] - prev) % K
        moved = np.where(step < K / 2, step, step - K) * fw.cl_ds
        # one control step moves a car less than 0.5 m along the loop, never half a lap
        # (except a car respawned elsewhere after touching another)
        jumps = int((np.abs(moved[fw.active[:, 1:]]) >= 0.5).sum())
        assert jumps <= fw.respawns - respawns
    # traffic does not yield at the junction: some cars meet there and respawn, most pass
    assert fw.respawns <= 40


# --------------------------------------------------------------------------- training
def test_ppo_runs_on_the_fast_vecenv():
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecMonitor

    torch.set_num_threads(1)
    venv = VecMonitor(FastVecEnv(n_envs=16, seed=0))
    model = PPO("MlpPolicy", venv, n_steps=128, batch_size=64, n_epochs=2, seed=0, verbose=0,
                policy_kwargs=dict(net_arch=[64, 64], activation_fn=torch.nn.Tanh))
    model.learn(4096)
    assert model.num_timesteps >= 4096
    act, _ = model.predict(venv.reset(), deterministic=True)
    assert act.shape == (16, 2)


def test_parallel_lidar_gives_the_same_scans():
    worlds = [FastWorld(n_envs=4, obstacle_lidar=True, seed=0, parallel=p) for p in (False, True)]
    acts = np.random.default_rng(0).uniform(-1, 1, (10, 4, 2))
    for fw in worlds:
        fw.reset()
        for a in acts:
            fw.step(a)
    assert np.array_equal(worlds[0].ranges, worlds[1].ranges)


def test_non_finite_actions_are_counted_and_neutralised():
    fw = FastWorld(n_envs=2, n_obstacles=0, seed=0)
    fw.reset()
    obs, (thr, a_d), col, _ = fw.step(np.array([[np.nan, 0.2], [1.0, np.inf]]))
    assert fw.bad_actions == 2
    assert np.isfinite(fw.agent_state()).all() and np.isfinite(obs).all()
    assert thr[0] == 0.0 and a_d[1] == 1.0


def test_respawned_obstacles_keep_away_from_the_agent():
    fw = FastWorld(n_envs=1, n_obstacles=15, seed=0)
    fw.reset()
    for _ in range(30):
        fw.wall_hit[0, 1:] = True  # every obstacle "touched a wall": all respawn
        fw._respawn_obstacles(np.zeros(1, dtype=bool))
        d = np.hypot(fw.x[0, 1:] - fw.x[0, 0], fw.y[0, 1:] - fw.y[0, 0])
        act = fw.active[0, 1:]
        assert np.all(d[act] >= 6.0)
        px, py = fw.x[0, 1:][act], fw.y[0, 1:][act]
        dd = np.hypot(px[:, None] - px[None], py[:, None] - py[None]) + np.eye(act.sum()) * 99
        assert dd.min() >= 2.5


def test_chunk_culling_is_exact():
    """Skipping out-of-range, out-of-fan and occluded wall chunks changes no range at all."""
    from racecav.sim import fast_kernels as K

    fw = FastWorld(n_envs=16, obstacle_lidar=True, seed=1)
    fw.reset()
    no_cull = np.array([[0.0, 0.0, 1e9, 0, len(fw.faces)]])
    rng = np.random.default_rng(2)
    for _ in range(5):
        for _ in range(8):
            fw.step(np.stack([rng.uniform(0, 1, 16), rng.uniform(-1, 1, 16)], 1))
        ref = np.empty_like(fw.ranges)
        K.lidar(fw.x, fw.y, fw.yaw, fw.active, fw.observe, fw.faces, no_cull, fw.corners, fw.mount,
                fw.ray_c, fw.ray_s, fw.ray_t, fw.spec.angle_min, fw.spec.angle_increment,
                fw.spec.range_max, ref)
        assert np.array_equal(ref, fw.ranges)


@pytest.mark.parametrize("backend", ["fast", "bullet"])
def test_policy_traffic_driver(backend):
    """A policy callable drives the obstacle cars on their own scans, on both backends."""
    seen = []

    def policy(obs):
        seen.append(obs.shape)
        return np.tile([0.8, 0.0], (len(obs), 1))

    env = OvertakeEnv(backend=backend, n_obstacles=3, driver=policy)
    try:
        env.reset(seed=0)
        for _ in range(5):
            env.step(np.array([0.0, 0.0], np.float32))
        assert seen and seen[-1] == (3, 170)
    finally:
        env.close()


def test_curriculum_draws_the_failing_family_more(tmp_path):
    """A full-throttle straight car wins the paper-timed crossing and loses the conflict-timed
    one: the curriculum learns both rates and then draws the failing file about 10x as often."""
    import shutil

    from racecav.common.config import EnvConfig
    from racecav.common.scenario import SCENARIOS_DIR
    from racecav.training.vec_env import FamilyCurriculum

    for name in ("right-to-left", "conflict-right-to-left"):
        shutil.copy(SCENARIOS_DIR / f"{name}.toml", tmp_path / f"{name}.toml")
    cfg = EnvConfig(n_envs=16, scenarios=str(tmp_path), scenario_share=1.0, curriculum=True, n_obstacles=0)
    env = FastVecEnv(config=cfg, seed=3)
    cur = env.curriculum
    assert isinstance(cur, FamilyCurriculum) and cur.names == ["conflict-right-to-left", "right-to-left"]
    (world,) = cur.worlds
    assert np.allclose(world.draw_p, 0.5)  # nothing known yet: equal weights
    env.reset()
    drawn = {n: 0 for n in cur.names}
    episodes = 0
    while episodes < 400:
        env.step_async(np.tile([1.0, 0.0], (env.num_envs, 1)))
        _, _, dones, infos = env.step_wait()
        episodes += int(dones.sum())
        if episodes > 200:  # after the rates are known: count what the resets draw
            for n in np.flatnonzero(dones):
                drawn[cur.names[cur.fam_of[0][world.scenario_index[n]]]] += 1
    rates = cur.success_rates()
    assert rates["right-to-left"] > 0.9 and rates["conflict-right-to-left"] < 0.1
    p = dict(zip(cur.names, world.draw_p))
    assert p["conflict-right-to-left"] > 8 * p["right-to-left"]
    assert drawn["conflict-right-to-left"] > 4 * drawn["right-to-left"] > 0


def test_curriculum_flag_is_recorded():
    import argparse

    from racecav.training.cli import add_arguments, config_from_args

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["overtake", "--scenarios", "conflicts", "--curriculum"])
    assert config_from_args(args).env.curriculum is True
    args = parser.parse_args(["overtake", "--scenarios", "conflicts"])
    assert config_from_args(args).env.curriculum is False


def test_curriculum_boost_weights_a_family_and_names_a_wrong_one(tmp_path):
    """--curriculum-boost FAMILY=W multiplies that family's draw weight (before any episode both
    weigh 0.5); it is recorded in the run config, and a family the scenarios lack is an error
    listing the ones they have."""
    import argparse
    import shutil

    import pytest

    from racecav.common.config import EnvConfig
    from racecav.common.scenario import SCENARIOS_DIR
    from racecav.training.cli import add_arguments, config_from_args

    for name in ("right-to-left", "conflict-right-to-left"):
        shutil.copy(SCENARIOS_DIR / f"{name}.toml", tmp_path / f"{name}.toml")
    base = dict(n_envs=8, scenarios=str(tmp_path), scenario_share=1.0, curriculum=True, n_obstacles=0)
    env = FastVecEnv(config=EnvConfig(**base, curriculum_boost="right-to-left=3"), seed=0)
    (world,) = env.curriculum.worlds
    p = dict(zip(env.curriculum.names, world.draw_p))
    assert p["right-to-left"] == pytest.approx(3 * p["conflict-right-to-left"])
    env.close()
    with pytest.raises(ValueError, match="no family cross-left.*families: conflict-right-to-left, right-to-left"):
        FastVecEnv(config=EnvConfig(**base, curriculum_boost="cross-left=2"), seed=0)
    for bad in ("right-to-left", "right-to-left=0", "=2"):
        with pytest.raises(ValueError, match="curriculum_boost"):
            EnvConfig(**base, curriculum_boost=bad)
    with pytest.raises(ValueError, match="set curriculum too"):
        EnvConfig(**{**base, "curriculum": False}, curriculum_boost="right-to-left=3")
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["overtake", "--scenarios", "conflicts", "--curriculum",
                              "--curriculum-boost", "conflicts/cross-left=2, conflicts/head-on=1.5"])
    assert config_from_args(args).env.curriculum_boost == {"conflicts/cross-left": 2.0, "conflicts/head-on": 1.5}



