"""Lidar views: the wide scan holds every view exactly, both backends see the same wide scan, a
policy starts from one trained on another view with the same behaviour, and the services take
each controller's view out of whatever scan the sim or the sensor publishes."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from racecav.common import keys, procs
from racecav.common.client import get_status
from racecav.common.codec import encode
from racecav.common.lidar import VIEWS, WIDE_SCAN, make_scan, published_scan, ray_angles, sanitize, view_index
from racecav.common.policy import load_policy
from racecav.common.vehicle import load_car
from tests.test_controllers_policy import Commands, random_policy_file

PAPER, WIDE = VIEWS["paper"], VIEWS["wide"]


def _wait(pred, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def test_the_wide_scan_holds_every_view_ray_for_ray():
    a = ray_angles(WIDE_SCAN).astype(np.float64)
    i = view_index(WIDE_SCAN, PAPER)
    assert i.tolist() == list(range(84, 254))  # the paper's 170 rays, the same angles
    assert np.abs(a[i] - ray_angles(PAPER)).max() < 1e-6
    j = view_index(WIDE_SCAN, WIDE)
    assert j.tolist() == list(range(0, 338, 2))
    assert np.degrees(ray_angles(WIDE)[[0, -1]]) == pytest.approx([-89.73, 89.20], abs=0.01)
    assert published_scan(load_car().lidar, "paper") == load_car().lidar
    assert published_scan(load_car().lidar, "wide").n_rays == 338
    with pytest.raises(ValueError, match="does not hold the view of 169 rays"):
        view_index(PAPER, WIDE)
    with pytest.raises(ValueError, match="expected 'paper' or 'wide'"):
        published_scan(PAPER, "360")


@pytest.mark.parametrize("name", ["conflict-left-to-right", "racetrack"])
def test_both_backends_see_the_same_wide_scan(name):
    """PyBullet's rays and the fast world's at PyBullet's poses: the wide scan agrees as well as
    the paper's does (measured 93-96 % of rays within 2 cm for both; grazing rays at car and
    wall edges make the rest)."""
    from racecav.common.scenario import load_scenario
    from racecav.sim.bullet_world import BulletWorld
    from racecav.sim.fast_world import FastWorld

    sc = load_scenario(name)
    car = load_car().model_copy(update={"lidar": WIDE_SCAN})
    bw = BulletWorld(sc, car=car)
    try:
        bw.reset(seed=5)
        if sc.world == "racetrack":
            fw = FastWorld(n_envs=1, car=car, n_obstacles=0)
            fw.reset(seed=0)
        else:
            fw = FastWorld(n_envs=1, scenarios=[sc], car=car)
            fw.reset(seed=0)
            fw.place_trial(0, 0, bw.trial)
        rng = np.random.default_rng(1)
        err = []
        for _ in range(30):
            a = np.array([[0.6, 0.3 * rng.uniform(-1, 1)]])
            obs, _, col, _ = bw.step(a)
            fw.step(a)
            x, y, yaw, v = bw.agent_state()[0]
            fw.set_state(0, 0, x=x, y=y, yaw=yaw, v=v)  # rescans at PyBullet's pose
            err.append(np.abs(obs[0] - fw.agent_obs()[0]))
            if col[0]:
                break
        err = np.stack(err)
        assert err.shape[1] == 338
        outer = np.r_[0:84, 254:338]  # the rays the paper's view does not have
        assert (err < 0.02).mean() > 0.9 and (err[:, outer] < 0.02).mean() > 0.9
    finally:
        bw.close()


def test_weights_mapped_to_a_wider_view_act_the_same():
    """map_inputs: a first layer of the paper's view (2 scans) on the wide view gives the same
    pre-activations when neighbouring paper rays agree (two of them fall on one wide ray), and
    zero weight on the rays the paper's view never saw."""
    from racecav.training.train import map_inputs

    rng = np.random.default_rng(0)
    w = rng.normal(size=(64, 2 * PAPER.n_rays))
    w_wide = map_inputs(w, PAPER, WIDE, n_stack=2)
    assert w_wide.shape == (64, 2 * WIDE.n_rays)
    x_wide = rng.uniform(0.1, 12, (5, 2, WIDE.n_rays))
    x_paper = np.repeat(x_wide[:, :, 42:127], 2, axis=2)  # rays 84+2k and 85+2k of the fine grid
    np.testing.assert_allclose(x_paper.reshape(5, -1) @ w.T, x_wide.reshape(5, -1) @ w_wide.T, atol=1e-9)
    outside = np.r_[0:42, 127:169]
    assert not w_wide.reshape(64, 2, -1)[:, :, outside].any()
    # a one-scan policy into two scans: the second slot starts at zero
    w1 = map_inputs(w[:, :170], PAPER, WIDE, n_stack=2)
    assert not w1[:, 169:].any() and w1[:, :169].any()
    # statistics: each wide ray takes its nearest paper ray's (the outer ones the edge rays')
    mean = np.tile(np.arange(170.0), 2)
    m = map_inputs(mean, PAPER, WIDE, n_stack=2, stats=True)
    assert m.shape == (338,) and m[0] == 0 and m[168] == 169 and m[42] == 0 and m[43] == 2


def test_init_from_a_paper_checkpoint_keeps_its_actions(tmp_path):
    """init_weights of a wide-view model from the shipped paper-view `avoid`: the same action
    means on scans whose neighbouring paper rays agree."""
    import torch
    from stable_baselines3 import PPO

    from racecav.common.config import EnvConfig
    from racecav.common.policy import MODELS_DIR
    from racecav.training.train import init_weights
    from racecav.training.vec_env import FastVecEnv

    torch.set_num_threads(1)
    src_zip = MODELS_DIR / "avoid.zip"
    if json.loads(src_zip.with_suffix(".json").read_text()).get("lidar", "paper") != "paper":
        src_zip = MODELS_DIR / "avoid-paper.zip"
    src = PPO.load(src_zip, device="cpu")
    stack = src.observation_space.shape[0] // PAPER.n_rays
    venv = FastVecEnv(n_envs=2, config=EnvConfig(world="intersection", n_obstacles=0, lidar="wide",
                                                 obs_stack=stack, scenarios="head-to-head"), seed=0)
    model = PPO("MlpPolicy", venv, device="cpu", policy_kwargs=dict(net_arch=[64, 64], activation_fn=torch.nn.Tanh))
    init_weights(model, src_zip, view=WIDE)
    rng = np.random.default_rng(1)
    x_wide = rng.uniform(0.2, 12, (8, stack, WIDE.n_rays)).astype(np.float32)
    x_paper = np.repeat(x_wide[:, :, 42:127], 2, axis=2)

    def mean(m, x):
        with torch.no_grad():
            return m.policy.get_distribution(torch.as_tensor(x.reshape(len(x), -1))).distribution.mean.numpy()

    np.testing.assert_allclose(mean(model, x_wide), mean(src, x_paper), atol=1e-5)


def test_policy_takes_its_view_from_a_wider_scan(spawn, session, tmp_path):
    """A paper-view policy answers a wide scan exactly as the paper scan made of its rays; a
    wide-view policy answers it from its own rays and refuses a paper scan (malformed)."""
    paper = random_policy_file(tmp_path / "paper.npz", seed=5)
    wide = random_policy_file(tmp_path / "wide.npz", seed=6, view="wide")
    rng = np.random.default_rng(2)
    ranges = rng.uniform(0.3, 8.0, WIDE_SCAN.n_rays).astype(np.float32)
    ranges[:20] = np.inf
    scan = make_scan(ranges, 1_000_000, 0, "sim", WIDE_SCAN)
    for path in (paper, wide):
        ctl = spawn("policy", "--model", str(path))
        procs.wait_alive(session, "car0", "policy", proc=ctl)
        cmds = Commands(session)
        pub = session.declare_publisher(keys.topic("car0", keys.SCAN))
        pub.put(encode(scan))
        (cmd,) = cmds.wait(1)
        pol = load_policy(path)
        a = pol(sanitize(ranges[view_index(WIDE_SCAN, pol.lidar)], pol.lidar))
        assert cmd.a_throttle == pytest.approx(float(a[0]), abs=1e-5)
        assert cmd.a_steer == pytest.approx(float(a[1]), abs=1e-5)
        if path == wide:  # the paper's scan does not hold the wide view
            pub.put(encode(make_scan(ranges[84:254], 2_000_000, 1, "sim", PAPER)))
            _wait(lambda: get_status(session, "car0", "policy").info["malformed"] >= 1, 5)
            assert len(cmds.snapshot()) == 1
            assert get_status(session, "car0", "policy").info["lidar"] == "wide"
        pub.undeclare()
        cmds.sub.undeclare()
        procs.stop(ctl)


def test_sim_publishes_the_wide_scan_for_a_wide_policy(spawn, session, tmp_path):
    """SimConfig.scan = wide (what `racecav eval` sets for a wide-view policy): 338 rays, and a
    wide-view policy drives the sim with them."""
    from racecav.evaluation.harness import CONTROLLERS, scan_kind

    wide = random_policy_file(tmp_path / "wide.npz", seed=6, view="wide")
    sim = spawn("sim", "--scenario", "head-to-head", "--mode", "lockstep", env={"RACECAV_SIM__SCAN": "wide"})
    procs.wait_alive(session, "car0", "sim", proc=sim)
    ctl = spawn("policy", "--model", str(wide))
    procs.wait_alive(session, "car0", "policy", proc=ctl)
    _wait(lambda: get_status(session, "car0", "policy").info["answered"] >= 5, 30)
    st = get_status(session, "car0", "policy").info
    assert st["malformed"] == 0
    assert get_status(session, "car0", "sim").info["last_source"] == "policy"
    # the harness sets it from the policy's metadata
    assert scan_kind(CONTROLLERS["drl-reversed"]) == "paper"
    assert scan_kind(CONTROLLERS["drl-avoid"]) == json.loads(
        CONTROLLERS["drl-avoid"].model.with_suffix(".json").read_text()).get("lidar", "paper")
