"""Scan stacks with a stride (EnvConfig.obs_stride, policy metadata "obs_stride"): the training
env, the in-process evaluation and the policy service stack the same scans, and a model
re-strided from a consecutive-scan checkpoint starts with the old response to motion."""

from __future__ import annotations

import time

import numpy as np

from racecav.common.config import EnvConfig, load_config
from racecav.common.lidar import VIEWS, WIDE_SCAN, make_scan
from racecav.common.policy import NumpyPolicy, ScanStack

WIDE = VIEWS["wide"]


def test_scan_stack_keeps_scans_stride_apart_and_restarts_on_reset():
    s = ScanStack(3, stride=2)
    got = [s(np.full(2, float(i), np.float32)).copy() for i in range(6)]
    # newest first: scan i, i - 2, i - 4; before there is such a history the first scan stands in
    assert [g[::2].tolist() for g in got] == [[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 1, 0], [4, 2, 0], [5, 3, 1]]
    s.reset()
    assert s(np.full(2, 9.0, np.float32)).tolist() == [9.0] * 6
    np.testing.assert_array_equal(s.current(), [9.0] * 6)


def test_fast_env_stacks_like_the_scan_stack_across_episode_ends():
    from racecav.common.scenario import SCENARIOS_DIR
    from racecav.training.vec_env import FastVecEnv

    cfg = EnvConfig(world="intersection", n_obstacles=0, lidar="wide", obs_stack=2, obs_stride=3,
                    scenarios=str(SCENARIOS_DIR / "conflict-head-to-head.toml"), scenario_share=1.0, n_envs=4)
    env = FastVecEnv(config=cfg, seed=3)
    obs = env.reset()
    r = WIDE.n_rays
    assert obs.shape == (4, 2 * r)
    stacks = [ScanStack(2, 3) for _ in range(4)]
    for i in range(4):
        stacks[i](obs[i, :r])
    rng = np.random.default_rng(0)
    ends = 0
    for _ in range(80):  # full throttle, random steering: episodes end by contact or time
        obs, _r, done, _info = env.step(np.stack([np.ones(4), rng.uniform(-1, 1, 4)], 1))
        for i in range(4):
            if done[i]:  # a new episode starts with no history
                stacks[i].reset()
                ends += 1
            np.testing.assert_array_equal(stacks[i](obs[i, :r]), obs[i])
    assert ends > 0


def _random_policy(stride: int, seed: int = 0) -> NumpyPolicy:
    rng = np.random.default_rng(seed)
    n = 2 * WIDE.n_rays
    arrays = {"w0": rng.normal(0, 0.15, (n, 64)), "b0": rng.normal(0, 0.1, 64),
              "w1": rng.normal(0, 0.2, (64, 64)), "b1": rng.normal(0, 0.1, 64),
              "w2": rng.normal(0, 0.3, (64, 2)), "b2": rng.normal(0, 0.1, 2)}
    return NumpyPolicy({k: v.astype(np.float32) for k, v in arrays.items()},
                       {"obs_stack": 2, "obs_stride": stride, "lidar": "wide"})


def test_policy_service_stacks_with_the_policy_s_stride():
    """The service's act path (fused kernel) on consecutive scans equals the numpy policy on the
    training stack; a lost scan (a seq gap) and a stamp that goes back with the next seq (a sim
    that swapped its world) restart the stack."""
    from racecav.common.lidar import sanitize
    from racecav.services.policy.service import PolicyService

    cfg = load_config(None)
    pol = _random_policy(stride=3)
    svc = PolicyService(cfg.model_copy(update={"policy": cfg.policy.model_copy(update={"backend": "fused"})}),
                        policy=pol)
    rng = np.random.default_rng(1)
    ref = ScanStack(2, 3)
    seq, back = 0, 0
    for k in range(16):
        seq += 2 if k == 7 else 1  # one scan lost before the 8th
        back += 3_000_000_000 if k == 12 else 0  # the 13th is stamped 2.9 s before the 12th
        ranges = rng.uniform(0.3, 10.0, WIDE_SCAN.n_rays).astype(np.float32)
        scan = make_scan(ranges, seq * 100_000_000 + 10_000_000_000 - back, seq, "sim", WIDE_SCAN)
        assert svc.check(scan, time.monotonic_ns())
        if k in (7, 12):
            ref.reset()
        want = pol(ref(sanitize(svc.view(scan), svc.spec)))
        np.testing.assert_allclose(svc.act(scan), want, atol=1e-5)


def test_restride_keeps_the_response_to_steady_motion():
    """A first layer trained on consecutive scans, re-strided for scans k apart: the same
    pre-activations when the scene changes steadily (scan t - k = scan t + k * step), and the
    same on a still scene."""
    from racecav.training.train import restride

    rng = np.random.default_rng(2)
    r, k = WIDE.n_rays, 4
    w = rng.normal(size=(64, 2 * r))
    w4 = restride(w, r, k)
    x = rng.uniform(0.2, 12, (5, r))
    step = rng.normal(0, 0.05, (5, r))
    old = np.concatenate([x, x + step], 1) @ w.T
    new = np.concatenate([x, x + k * step], 1) @ w4.T
    np.testing.assert_allclose(new, old, atol=1e-9)
    still = np.concatenate([x, x], 1)
    np.testing.assert_allclose(still @ w4.T, still @ w.T, atol=1e-9)
