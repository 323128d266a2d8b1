"""The fast VecEnv's scenario worlds drawn from a pool of maps (EnvConfig.scenario_maps,
training/map_pool.py), on generated roads maps (each file its own map)."""

from __future__ import annotations

import numpy as np
import pytest

from racecav.common.config import EnvConfig
from racecav.evaluation.benchmark import generate, load_benchmark
from racecav.training.vec_env import FastVecEnv


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    bf = load_benchmark("roads")
    bf = bf.model_copy(update={"families": [f for f in bf.families if f.control]})
    out = tmp_path_factory.mktemp("roads")
    generate(bf, out, seed=0, splits=("controls",), progress=False, n_test=1)
    return out / "controls"  # a folder: every file in it, 7 maps


def keys(env) -> list[str]:
    return [w.scenarios[0].world_key for w in env.worlds]


def test_scenario_worlds_come_from_a_pool_of_maps(maps):
    cfg = EnvConfig(scenarios=str(maps), scenario_share=1.0, scenario_maps=2, obs_stack=1)
    env = FastVecEnv(n_envs=5, config=cfg, seed=3)
    assert len(env.map_pool.keys) == 7
    assert len(env.worlds) == 2 and [w.n_envs for w in env.worlds] == [3, 2]
    obs = env.reset()
    seen = set(keys(env))
    for _ in range(6):
        before = keys(env)
        for _ in range(3):
            obs, _r, _d, _i = env.step(np.tile([1.0, 0.0], (5, 1)).astype(np.float32))
        env.resample_maps()
        assert [w.n_envs for w in env.worlds] == [3, 2]
        assert len(set(keys(env))) == 2  # two different maps at a time
        seen |= set(keys(env))
        # every world runs its own map's files, from a fresh start
        for w in env.worlds:
            assert {sc.world_key for sc in w.scenarios} == {w.scenarios[0].world_key}
            assert (w.time == 0).all()
        assert before != keys(env) or len(seen) > 2
    assert len(seen) >= 5  # over 7 draws of 2 of 7 maps
    obs2, *_ = env.step(np.zeros((5, 2), np.float32))
    assert obs2.shape == obs.shape and np.isfinite(obs2).all()


def test_scenario_maps_zero_builds_every_map(maps):
    env = FastVecEnv(n_envs=7, config=EnvConfig(scenarios=str(maps), scenario_share=1.0, obs_stack=1), seed=0)
    assert env.map_pool is None and len(env.worlds) == 7
    with pytest.raises(ValueError, match="scenario_maps"):
        env.resample_maps()
