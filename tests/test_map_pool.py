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


def test_selection_measures_every_map_of_a_pooled_run(maps, tmp_path):
    """select's suite cell of a run trained on K maps at a time runs one episode per map drawn
    (not the run's K maps), each source of its mix apart, families named by source."""
    import shutil

    from racecav.evaluation.inprocess import eval_suite_fast, reference_drivers

    drv = reference_drivers()["straight, full throttle"]
    families = {f.name for f in load_benchmark("roads").families if f.control}
    cfg = EnvConfig(scenarios=str(maps), scenario_share=1.0, scenario_maps=2, obs_stack=1)
    r = eval_suite_fast(drv, cfg, 7)
    assert r["suite_episodes"] == 7
    assert {k[6:] for k in r if k.startswith("suite_")} - {"success", "episodes"} == families  # all 7 maps
    other = shutil.copytree(maps, tmp_path / "again")
    two = eval_suite_fast(drv, cfg.model_copy(update={"scenarios": f"{maps},{other}"}), 14)
    assert {k[6:] for k in two if k.startswith("suite_")} - {"success", "episodes"} == \
        {f"{src}/{f}" for src in ("controls", "again") for f in families}
    assert two["suite_success"] == pytest.approx(r["suite_success"])  # the same maps, the same seeds
