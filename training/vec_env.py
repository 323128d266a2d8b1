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
from racecav.common.vehicle import brake_from_action
from racecav.training.env import env_settings, make_worlds, reward
from racecav.training.expert import latch_seen, tracking_steer
from racecav.training.flow_reward import flow_reward, flow_weights
from racecav.training.hold_heading import HoldRoad
from racecav.training.privileged import N_PRIVILEGED, privileged_features
from racecav.training.proximity import proximity_penalty


def family_mask(worlds, names: str, what: str = "hold_families") -> list[np.ndarray | None]:
    """Per FastWorld of ``worlds``: (files,) bool, the files whose family is one of ``names``
    (comma-separated: a suite, ``conflicts``; a family of every suite, ``cross-left``; or of one,
    ``conflicts/cross-left``; "": every file); None for a world without scenarios. A name that
    matches no family of any of the worlds is an error that starts with ``what`` (the setting it
    came from); a world may lack it (the road world has no crossings)."""
    wanted = [n.strip() for n in names.split(",") if n.strip()]
    out, matched = [], set()
    for w in worlds:
        if w.actors is None:
            out.append(None)
            continue
        fams = w.scenario_families
        if not wanted:
            out.append(np.ones(len(fams), dtype=bool))
            continue
        parts = [(f, *f.rpartition("/")[::2]) for f in fams]  # (suite/family, suite, family)
        matched |= {n for n in wanted if any(n in p for p in parts)}
        out.append(np.array([any(n in p for n in wanted) for p in parts]))
    unknown = [n for n in wanted if n not in matched]
    if unknown:
        have = sorted({f for w in worlds if w.actors is not None for f in w.scenario_families})
        raise ValueError(f"{what}: {', '.join(unknown)} is not a suite or family of the scenarios ({', '.join(have)})")
    return out


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
    :param privileged: append the critic's privileged features to each observation (after the
        scans; training/privileged.py).
    :param hold_until_seen: PPO's rollouts only (TrainConfig.hold_until_seen): in a scenario world
        the ego is driven straight along its road at full throttle, whatever the action, while
        ``held`` says so (no car has yet returned a ray of its scan this episode and it is short
        of its conflict point). Evaluation never sets it.
    :param hold_families: the scenario families it holds (TrainConfig.hold_families; "": all).
    :param hold_through: of those, the families held to the conflict point even once a car is
        in view (TrainConfig.hold_through; "": none).
    :param seed: seed of the reset randomisation (also settable with ``seed()``).
    """

    def __init__(self, n_envs: int | None = None, config: EnvConfig | None = None, *,
                 heading: str | None = None, n_obstacles: int | None = None, driver=None,
                 control_period: float | None = None, time_limit: float | None = None,
                 world: str | None = None, car: str | None = None,
                 agent_speed_scale: float | None = None, parallel: bool | None = None,
                 scenarios: str | None = None, scenario_share: float | None = None,
                 contact_penalty: float | None = None, obs_stack: int | None = None,
                 progress_reward: float | None = None, brake_below: float | None = None,
                 lane_keeping: float | None = None, privileged: bool = False, seed: int | None = None,
                 hold_until_seen: bool = False, hold_families: str = "", hold_through: str = ""):
        drv_obj = driver if driver is not None and not isinstance(driver, str) else None
        self.settings = env_settings(config, backend="fast", heading=heading,
                                     n_obstacles=n_obstacles,
                                     driver=driver if isinstance(driver, str) else None,
                                     control_period_s=control_period, time_limit_s=time_limit,
                                     world=world, car=car, agent_speed_scale=agent_speed_scale,
                                     n_envs=n_envs, parallel=parallel, scenarios=scenarios,
                                     scenario_share=scenario_share, contact_penalty=contact_penalty,
                                     obs_stack=obs_stack, progress_reward=progress_reward, brake_below=brake_below,
                                     lane_keeping=lane_keeping)
        # the batch: traffic worlds first, then one scenario world per scenario world geometry
        self.worlds = make_worlds(self.settings, n_envs=self.settings.n_envs, seed=seed, driver=drv_obj)
        self.world = self.worlds[0]
        n = sum(w.n_envs for w in self.worlds)
        spec = self.world.spec
        self.n_stack, self.stride = self.settings.obs_stack, self.settings.obs_stride
        self.privileged = privileged
        n_obs = self.n_stack * spec.n_rays
        low, high = np.full(n_obs, spec.range_min, np.float32), np.full(n_obs, spec.range_max, np.float32)
        if privileged:
            low = np.concatenate([low, np.full(N_PRIVILEGED, -np.inf, np.float32)])
            high = np.concatenate([high, np.full(N_PRIVILEGED, np.inf, np.float32)])
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
        self.lane_keeping = None
        if self.settings.lane_keeping and self.is_scenario.any():
            from racecav.training.lane_keeping import LaneKeeping

            self.lane_keeping = LaneKeeping(self.worlds, self.slices, self.settings.lane_keeping,
                                            self.settings.lane_keeping_horizon_s)
        self.hold_heading = HoldRoad.from_settings(n, self.settings) if self.is_scenario.any() else None
        self.hold_until_seen = hold_until_seen and bool(self.is_scenario.any())
        held = self.hold_until_seen
        self._hold_file = family_mask(self.worlds, hold_families) if held else [None] * len(self.worlds)
        self._through = (family_mask(self.worlds, hold_through, "hold_through") if held and hold_through
                         else [None] * len(self.worlds))
        self._seen = np.zeros(n, dtype=bool)  # hold_until_seen: a car has been in view this episode
        self.held = np.zeros(n, dtype=bool)
        """(N,) the worlds whose next action is overridden (hold_until_seen), for the state of the
        newest observation: the imitation term's ``--expert hold`` labels read it."""
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
        if self.hold_heading is not None:
            self.hold_heading.seen[:] = False
        self.reset_infos = [{} for _ in range(self.num_envs)]
        self._stack[:] = obs[:, None]
        self._update_held()
        return self._stacked()

    def _update_held(self) -> None:
        """``held`` for the worlds' current state (after a step and its resets)."""
        if not self.hold_until_seen:
            return
        for w, sl, files, through in zip(self.worlds, self.slices, self._hold_file, self._through):
            if files is not None:
                mine = files[w.scenario_index]
                # held-through worlds are held whatever is in view: no scan for their latch
                thru = np.zeros(len(mine), bool) if through is None else through[w.scenario_index]
                envs = np.flatnonzero(mine & ~thru)
                seen = self._seen[sl]  # a view: updated in place
                seen[envs] = latch_seen(w, seen[envs], envs)
                # every scenario's ego drives along +x to its conflict point at x = 0
                self.held[sl] = mine & (~seen | thru) & (w.x[:, 0] < 0.0)

    def _stacked(self) -> np.ndarray:
        """The observations: each world's ``n_stack`` scans ``stride`` apart, newest first, flattened
        (then the critic's privileged features of the worlds' current state, if asked)."""
        obs = self.stacked_view(self.n_stack, self.stride)
        if self.privileged:
            return np.concatenate([obs, np.concatenate([privileged_features(w) for w in self.worlds])], axis=1)
        return obs

    def stacked_view(self, n_stack: int, stride: int) -> np.ndarray:
        """The raw scans as a policy with its own ``n_stack`` and ``stride`` sees them (e.g. a frozen
        teacher trained with consecutive scans labelling a run with a longer stride), from the
        history this env keeps.

        :raises ValueError: when that view needs scans older than the history holds."""
        if (n_stack - 1) * stride + 1 > self._stack.shape[1]:
            raise ValueError(f"a stack of {n_stack} scans {stride} apart needs more history than this env's "
                             f"{self.n_stack} scans {self.stride} apart")
        return self._stack[:, ::stride][:, :n_stack].reshape(self.num_envs, -1).copy()

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions, dtype=np.float64).reshape(self.num_envs, 2)

    def step_wait(self) -> VecEnvStepReturn:
        obs_parts, thr, a_d, col, trunc, succ, dprog = [], [], [], [], [], [], []
        if self.hold_until_seen and self.held.any():  # straight at full throttle until a car is seen
            self._actions = self._actions.copy()
            for w, sl in zip(self.worlds, self.slices):
                h = self.held[sl]
                if h.any():
                    self._actions[sl][h] = np.stack([np.ones(int(h.sum())), tracking_steer(w)[h]], axis=1)
        # from the state the actions are taken in
        lane = self.lane_keeping.penalty(self._actions) if self.lane_keeping is not None else None
        flow = [] if self.settings.flow_reward else None
        hold = [] if self.hold_heading is not None else None
        near = [] if self.settings.proximity_penalty else None
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
            if hold is not None:  # the state the step led to: its heading, and what the new scan shows
                hold.append(self.hold_heading.step(w, sl, a[:, 0]))
            if near is not None:
                near.append(proximity_penalty(self.settings.proximity_penalty, w))
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
        if self.settings.contact_penalty:
            rewards = rewards + np.float32(self.settings.contact_penalty) * collided
        if self.settings.progress_reward:
            rewards = rewards + (self.settings.progress_reward * np.concatenate(dprog)).astype(np.float32)
        if lane is not None:
            rewards = rewards + lane
        if flow is not None:
            rewards = rewards + np.concatenate(flow)
        if hold is not None:
            rewards = rewards + np.concatenate(hold)
        if near is not None:
            rewards = rewards + np.concatenate(near)
        self.a_prev[:] = a_delta
        self._stack[:, 1:] = self._stack[:, :-1]
        self._stack[:, 0] = obs
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
            if self.hold_heading is not None:
                self.hold_heading.reset(dones)
            if self.curriculum is not None:
                self.curriculum.update()
        self._update_held()
        return obs, rewards, dones, infos

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
