"""FastVecEnv: a stable-baselines3 VecEnv over one FastWorld batch (no Python loop per env).

``FastVecEnv(n_envs=64, heading="reversed")`` is N copies of ``racecav/Overtake-v0`` (fast
backend) stepped by one numba call chain. Semantics are SB3's: done envs are reset inside
``step_wait``; their last observation is in ``infos[i]["terminal_observation"]`` and
``infos[i]["TimeLimit.truncated"]`` is True when the time limit (not a contact) ended the
episode; scenario episodes also report ``infos[i]["is_success"]``. Wrap it in ``VecMonitor`` for
episode returns and lengths.

With ``scenarios`` and ``scenario_share`` a share of the batch runs scenario episodes (the
conflict suite's train split: triggered, synchronised kinematic actors, sim/actors.py), one
FastWorld per scenario world geometry, beside the traffic worlds; each scenario episode ends at
its scenario's duration.
"""

from __future__ import annotations

from collections import deque
from typing import Any, Sequence

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvStepReturn

from racecav.common.config import EnvConfig
from racecav.common.policy import push_scans, stacked_scans
from racecav.common.vehicle import brake_from_action
from racecav.training.env import env_settings, make_worlds, reward, scenario_envs
from racecav.training.flow_reward import flow_reward, flow_weights


class FamilyCurriculum:
    """Draw scenario files by family, each family weighted by its recent failure rate.

    A family that the policy passes is still drawn (weight ``FLOOR``), so it is not forgotten;
    ``boost`` multiplies a family's weight (EnvConfig.curriculum_boost); files of a family stay
    equally likely. Families are grouped across the batch's scenario
    worlds (a family may span world geometries); each world's draw is renormalised. The
    history is not checkpointed: a resumed run relearns it in its first episodes.
    """

    WINDOW = 200  # episodes per family in the failure rate
    FLOOR = 0.1
    MIN_EPISODES = 20  # before this, a family counts as failing half the time

    def __init__(self, worlds: list, boost: dict[str, float] | None = None):
        self.worlds = [w for w in worlds if w.actors is not None]
        self.names = sorted({f for w in self.worlds for f in w.scenario_families})
        unknown = sorted(set(boost or {}) - set(self.names))
        if unknown:
            raise ValueError(f"curriculum_boost: no family {', '.join(unknown)} in the scenarios "
                             f"(families: {', '.join(self.names)})")
        self.boost = np.array([(boost or {}).get(f, 1.0) for f in self.names])
        ids = {f: i for i, f in enumerate(self.names)}
        self.fam_of = [np.array([ids[f] for f in w.scenario_families]) for w in self.worlds]
        self._files_of_fam = [np.bincount(fam, minlength=len(self.names))[fam] for fam in self.fam_of]
        self.history = [deque(maxlen=self.WINDOW) for _ in self.names]
        self.update()

    def record(self, world, envs: np.ndarray, success: np.ndarray) -> None:
        """Episodes of ``world``'s ``envs`` ended (before their reset draws the next file)."""
        fam = self.fam_of[self.worlds.index(world)]
        for n, ok in zip(envs, success):
            self.history[fam[world.scenario_index[n]]].append(bool(ok))

    def success_rates(self) -> dict[str, float]:
        """Family -> success rate over its window (NaN before MIN_EPISODES episodes)."""
        return {f: (float(np.mean(h)) if len(h) >= self.MIN_EPISODES else float("nan"))
                for f, h in zip(self.names, self.history)}

    def update(self) -> None:
        rate = np.array(list(self.success_rates().values()))
        weight = np.maximum(1.0 - np.where(np.isnan(rate), 0.5, rate), self.FLOOR) * self.boost
        for w, fam, n_files in zip(self.worlds, self.fam_of, self._files_of_fam):
            p = weight[fam] / n_files
            w.draw_p = p / p.sum()


class FastVecEnv(VecEnv):
    """N fast overtaking worlds as one SB3 VecEnv.

    :param n_envs: worlds in the batch (default: config env.n_envs).
    :param config: EnvConfig to start from; keyword overrides as in OvertakeEnv (heading,
        n_obstacles, driver, control_period, time_limit, world, car, agent_speed_scale,
        parallel: the lidar on numba's threads).
    :param seed: seed of the reset randomisation (also settable with ``seed()``).
    """

    def __init__(self, n_envs: int | None = None, config: EnvConfig | None = None, *,
                 heading: str | None = None, n_obstacles: int | None = None, driver=None,
                 control_period: float | None = None, time_limit: float | None = None,
                 world: str | None = None, car: str | None = None,
                 agent_speed_scale: float | None = None, parallel: bool | None = None,
                 scenarios: str | None = None, scenario_share: float | None = None,
                 obs_stack: int | None = None, progress_reward: float | None = None,
                 brake_below: float | None = None, seed: int | None = None):
        drv_obj = driver if driver is not None and not isinstance(driver, str) else None
        self.settings = env_settings(config, backend="fast", heading=heading,
                                     n_obstacles=n_obstacles,
                                     driver=driver if isinstance(driver, str) else None,
                                     control_period_s=control_period, time_limit_s=time_limit,
                                     world=world, car=car, agent_speed_scale=agent_speed_scale,
                                     n_envs=n_envs, parallel=parallel, scenarios=scenarios,
                                     scenario_share=scenario_share, obs_stack=obs_stack,
                                     progress_reward=progress_reward, brake_below=brake_below)
        # the batch: traffic worlds first, then one scenario world per scenario world geometry (or
        # per map drawn from a pool: EnvConfig.scenario_maps, training/map_pool.py)
        self.map_pool, self.map_rng = None, np.random.default_rng(seed)
        n_scen = scenario_envs(self.settings, self.settings.n_envs)
        if self.settings.scenario_maps and n_scen:
            from racecav.training.map_pool import MapPool

            self.map_pool = MapPool(self.settings, n_scen)
        self.worlds = make_worlds(self.settings, n_envs=self.settings.n_envs, seed=seed, driver=drv_obj,
                                  map_pool=self.map_pool, map_rng=self.map_rng)
        self.world = self.worlds[0]
        n = sum(w.n_envs for w in self.worlds)
        spec = self.world.spec
        self.n_stack, self.stride = self.settings.obs_stack, self.settings.obs_stride
        n_obs = self.n_stack * spec.n_rays
        low, high = np.full(n_obs, spec.range_min, np.float32), np.full(n_obs, spec.range_max, np.float32)
        obs_space = gym.spaces.Box(low, high, dtype=np.float32)
        act_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.render_mode = None
        super().__init__(n, obs_space, act_space)
        bounds = np.cumsum([0] + [w.n_envs for w in self.worlds])
        self.slices = [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]
        self.is_scenario = np.zeros(n, dtype=bool)
        for w, sl in zip(self.worlds, self.slices):
            self.is_scenario[sl] = w.actors is not None
        self.a_prev = np.zeros(n, dtype=np.float64)
        self._actions = np.zeros((n, 2))
        # each world's newest (n_stack - 1) * stride + 1 scans, newest first (common/policy.ScanStack)
        self._stack = np.zeros((n, (self.n_stack - 1) * self.stride + 1, spec.n_rays), np.float32)
        self.curriculum = FamilyCurriculum(self.worlds, self.settings.curriculum_boost) if self.settings.curriculum and self.is_scenario.any() else None
        if seed is not None:
            self.seed(seed)

    @property
    def steps(self) -> np.ndarray:
        """(N,) control steps of each world's current episode."""
        return np.concatenate([np.rint(w.time / w.control_period).astype(np.int64) for w in self.worlds])

    # --- VecEnv API -----------------------------------------------------------------------
    def reset(self) -> np.ndarray:
        seed = self._seeds[0]
        obs = np.concatenate([w.reset(seed=None if seed is None else seed + 1_000_003 * k)
                              for k, w in enumerate(self.worlds)])
        self._reset_seeds()
        self._reset_options()
        self.a_prev[:] = 0.0
        self.reset_infos = [{} for _ in range(self.num_envs)]
        self._stack[:] = obs[:, None]
        return self._stacked()

    def _stacked(self) -> np.ndarray:
        """The observations: each world's ``n_stack`` scans ``stride`` apart, newest first, flattened."""
        return self.stacked_view(self.n_stack, self.stride)

    def stacked_view(self, n_stack: int, stride: int) -> np.ndarray:
        """The raw scans as a policy with its own ``n_stack`` and ``stride`` sees them (e.g. a frozen
        teacher trained with consecutive scans labelling a run with a longer stride), from the
        history this env keeps.

        :raises ValueError: when that view needs scans older than the history holds."""
        if (n_stack - 1) * stride + 1 > self._stack.shape[1]:
            raise ValueError(f"a stack of {n_stack} scans {stride} apart needs more history than this env's "
                             f"{self.n_stack} scans {self.stride} apart")
        return stacked_scans(self._stack, n_stack, stride)

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions, dtype=np.float64).reshape(self.num_envs, 2)

    def step_wait(self) -> VecEnvStepReturn:
        obs_parts, thr, a_d, col, trunc, succ, dprog = [], [], [], [], [], [], []
        flow = [] if self.settings.flow_reward else None
        for w, sl in zip(self.worlds, self.slices):
            p0 = w.progress()
            if flow is not None:  # the crossing cars' flow before the step, the ego's motion over it
                directions, x0, y0 = flow_weights(w), w.x[:, 0].copy(), w.y[:, 0].copy()
            a = self._actions[sl]
            bb = self.settings.brake_below  # None (the paper's action): no brake mask on the hot path
            o, (t, d), c, _info = w.step(a, brake=None if bb is None else brake_from_action(a[:, 0], bb))
            dprog.append(w.progress() - p0)
            if flow is not None:
                flow.append(flow_reward(self.settings.flow_reward, directions, w.x[:, 0] - x0, w.y[:, 0] - y0))
            obs_parts.append(o)
            thr.append(t)
            a_d.append(d)
            col.append(c)
            trunc.append((w.time >= w.time_limit - 1e-9) & ~c)
            succ.append(w.success() if w.actors is not None else np.zeros(w.n_envs, bool))
        obs = np.concatenate(obs_parts)
        collided, truncated = np.concatenate(col), np.concatenate(trunc)
        a_delta = np.concatenate(a_d)
        rewards = reward(np.concatenate(thr), self.a_prev, a_delta)
        if self.settings.progress_reward:
            rewards = rewards + (self.settings.progress_reward * np.concatenate(dprog)).astype(np.float32)
        if flow is not None:
            rewards = rewards + np.concatenate(flow)
        self.a_prev[:] = a_delta
        push_scans(self._stack, obs)
        obs = self._stacked()
        dones = collided | truncated
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        if dones.any():
            success = np.concatenate(succ)
            for i in np.flatnonzero(dones):
                infos[i]["terminal_observation"] = obs[i].copy()
                infos[i]["TimeLimit.truncated"] = bool(truncated[i])
                if self.is_scenario[i]:  # SB3's convention (evaluation helpers read it)
                    infos[i]["is_success"] = bool(success[i])
            for w, sl in zip(self.worlds, self.slices):
                idx = np.flatnonzero(dones[sl])
                if idx.size and self.curriculum is not None and w.actors is not None:
                    self.curriculum.record(w, idx, success[sl][idx])
                if idx.size:
                    w.reset_worlds(idx)
                    self._stack[sl][idx] = w.agent_obs()[idx][:, None]  # a new episode: no history
            obs = self._stacked()
            self.a_prev[dones] = 0.0
            if self.curriculum is not None:
                self.curriculum.update()
        return obs, rewards, dones, infos

    def resample_maps(self, seed: int | None = None) -> None:
        """Move the scenario worlds to K maps drawn afresh from the pool (EnvConfig.scenario_maps,
        training/map_pool.py), reset them and rebuild what holds the old worlds (the curriculum
        keeps its history, by family). It cuts their episodes: call it between rollouts."""
        if self.map_pool is None:
            raise ValueError("resample_maps: the env has no map pool (set scenario_maps)")
        rng = self.map_rng if seed is None else np.random.default_rng(seed)
        first = next(i for i, w in enumerate(self.worlds) if w.actors is not None)
        new = self.map_pool.build(self.map_pool.draw(rng), seed=int(rng.integers(2**31)))
        self.worlds[first:] = new
        self.world = self.worlds[0]
        for w, sl in zip(new, self.slices[first:]):
            self._stack[sl] = w.reset()[:, None]
            self.a_prev[sl] = 0.0
        if self.curriculum is not None:
            old = dict(zip(self.curriculum.names, self.curriculum.history))
            self.curriculum = FamilyCurriculum(self.worlds, self.settings.curriculum_boost)
            for name, h in zip(self.curriculum.names, self.curriculum.history):
                h.extend(old.get(name, ()))
            self.curriculum.update()

    def close(self) -> None:
        pass

    def seed(self, seed: int | None = None) -> Sequence[int | None]:
        """Seed the next reset (one RNG drives the whole batch's randomisation)."""
        if seed is None:
            seed = int(np.random.SeedSequence().generate_state(1)[0])
        self._seeds = [seed + i for i in range(self.num_envs)]
        return self._seeds

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        val = getattr(self, attr_name)
        return [val for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        setattr(self, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None,
                   **method_kwargs) -> list[Any]:
        out = getattr(self, method_name)(*method_args, **method_kwargs)
        return [out for _ in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        return [None for _ in range(self.num_envs)]
