"""Scenario worlds drawn from a pool of maps (EnvConfig.scenario_maps).

A FastWorld holds one world geometry, so the fast VecEnv builds one per map its scenarios use.
The conflict suite has a handful of maps; a generated roads suite carries its own map in every
file (its train split: hundreds). With ``scenario_maps = K`` the batch's scenario worlds are K
FastWorlds of equal size, each on one map drawn from the pool (its files, with their families),
and :meth:`FastVecEnv.resample_maps` draws K maps again: every few rollouts the batch moves to
other roads. The maps are drawn without replacement, each source of ``scenarios`` (a suite, a
folder, a file: the comma-separated parts) as often as any other, spread over its files: a suite
of 720 one-file maps does not crowd out one of 1,400 files on two maps. Inside a map its files
are drawn as before.

Resampling cuts the episodes running in the scenario worlds (a new episode starts there, with no
done flag): call it between rollouts of an imitation run (DAgger). A PPO run would need the cut
reported as a truncation.
"""

from __future__ import annotations

import numpy as np


class MapPool:
    """The scenario files of ``settings.scenarios`` (train split) grouped by map.

    :param settings: the EnvConfig (scenarios, scenario_maps, car, control period, parallel).
    :param n_envs: the scenario worlds' envs in all (split evenly over the K maps).
    """

    def __init__(self, settings, n_envs: int):
        from racecav.common.scenario import load_scenario, scenario_sources

        self.settings = settings
        self.groups: dict[str, tuple[list, list[str]]] = {}
        weight: dict[str, float] = {}
        parts = [p.strip() for p in str(settings.scenarios).split(",") if p.strip()]
        for part in parts:
            files = scenario_sources(part, "train")
            for f, family in files:
                sc = load_scenario(f)
                scs, fams = self.groups.setdefault(sc.world_key, ([], []))
                scs.append(sc)
                fams.append(family)
                weight[sc.world_key] = weight.get(sc.world_key, 0.0) + 1.0 / len(files)
        self.keys = list(self.groups)
        w = np.array([weight[k] for k in self.keys])
        self.p = w / w.sum()
        """(maps,) each map's draw probability: every source's share equal, spread over its files."""
        self.k = min(int(settings.scenario_maps), len(self.keys))
        if n_envs < self.k:
            raise ValueError(f"scenario_maps: {self.k} maps need at least as many scenario envs (have {n_envs})")
        base = n_envs // self.k
        self.sizes = [base + (1 if i < n_envs - base * self.k else 0) for i in range(self.k)]

    def draw(self, rng: np.random.Generator) -> list[str]:
        """K distinct maps (weighted by ``p``)."""
        return [self.keys[i] for i in rng.choice(len(self.keys), self.k, replace=False, p=self.p)]

    def build(self, keys: list[str], seed: int | None) -> list:
        """One FastWorld per map of ``keys``, sized by ``sizes``."""
        from racecav.sim.fast_world import FastWorld
        from racecav.training.env import env_car

        st = self.settings
        worlds = []
        for i, (key, n) in enumerate(zip(keys, self.sizes)):
            scs, fams = self.groups[key]
            w = FastWorld(n_envs=n, scenarios=scs, car=env_car(st), control_period=st.control_period_s,
                          seed=None if seed is None else seed + 7919 * (i + 1), parallel=st.parallel)
            w.scenario_families = fams  # the curriculum's grouping (training/vec_env.py)
            worlds.append(w)
        return worlds
