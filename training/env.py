"""``racecav/Overtake-v0``: the paper's training env (observation, action and reward exactly).

- Observation: the agent's 170 lidar ranges over the frontal 90 deg (float32, metres, index 0 =
  rightmost), the shared ``sanitize`` contract: no return -> range_max.
- Action: ``(a_T, a_delta)`` in [-1, 1]^2; ``T = clip(a_T, 0, 1)``; ``delta = clip(a_delta,
  delta_min, delta_max)`` (``steer_from_action`` of common/vehicle.py; steer_gain 1.0 rad/unit).
- Reward: ``5 T^2``, or ``-2.0`` when ``a_delta_prev * a_delta_curr == -1`` on the steering action
  clipped to [-1, 1] (a full-lock to full-lock reversal within one step). No collision penalty:
  a contact of the agent with a wall or a car terminates the episode; the time limit truncates.

Backends: ``fast`` (numba batched world, sim/fast_world.py) and ``bullet`` (the PyBullet
reference world, sim/bullet_world.py). For training use :class:`racecav.training.vec_env.
FastVecEnv`, which steps a whole batch of fast worlds without a Python loop per env.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from racecav.common.config import EnvConfig
from racecav.common.vehicle import brake_from_action

REVERSAL_PENALTY = -2.0
THROTTLE_REWARD_GAIN = 5.0


def reward(throttle, a_delta_prev, a_delta):
    """The paper's reward, vectorised.

    :param throttle: physical throttle T = clip(a_T, 0, 1).
    :param a_delta_prev: previous steering action clipped to [-1, 1] (0 at the episode start).
    :param a_delta: current steering action clipped to [-1, 1].
    :return: float32 array: -2.0 where a_delta_prev * a_delta == -1, else 5 T^2.
    """
    t = np.asarray(throttle, dtype=np.float64)
    rev = np.asarray(a_delta_prev, dtype=np.float64) * np.asarray(a_delta, dtype=np.float64) == -1.0
    return np.where(rev, REVERSAL_PENALTY, THROTTLE_REWARD_GAIN * t * t).astype(np.float32)


def env_settings(cfg: EnvConfig | None = None, **overrides) -> EnvConfig:
    """The env section of the config with keyword overrides applied (validated)."""
    cfg = cfg or EnvConfig()
    update = {k: v for k, v in overrides.items() if v is not None}
    # validate (model_copy would not): a bad option is an error naming the field
    return EnvConfig.model_validate({**cfg.model_dump(), **update}) if update else cfg


def env_car(settings: EnvConfig):
    """The car of ``settings`` as the env drives it: its control period and the policy's lidar
    view (EnvConfig.lidar) applied. Both backends take the scan from ``car.lidar``."""
    from racecav.common.lidar import VIEWS, with_rays
    from racecav.common.vehicle import load_car

    car = load_car(settings.car)
    update: dict[str, Any] = {"lidar": with_rays(car.lidar, VIEWS[settings.lidar])}
    if settings.control_period_s is not None:
        update["control_period_s"] = settings.control_period_s
    return car.model_copy(update=update)


def scenario_envs(settings: EnvConfig, n_envs: int) -> int:
    """How many of a batch's ``n_envs`` worlds run scenario episodes."""
    return int(round(settings.scenario_share * n_envs)) if settings.scenarios else 0


def make_worlds(settings: EnvConfig, n_envs: int, seed: int | None = None, driver=None,
                map_pool=None, map_rng=None) -> list:
    """The fast worlds of a batch of ``n_envs``: traffic worlds (``1 - scenario_share`` of
    them), then scenario worlds grouped by world geometry (sized by their number of files), or,
    with ``map_pool`` (training/map_pool.MapPool), on the pool's maps drawn by ``map_rng``."""
    from racecav.common.scenario import load_scenario, scenario_sources
    from racecav.sim.fast_world import FastWorld

    n_scen = scenario_envs(settings, n_envs)
    if settings.scenario_share > 0 and not settings.scenarios:
        raise ValueError("scenario_share: needs scenarios (a suite, folder or file)")
    worlds = []
    if n_envs - n_scen > 0:
        w = make_world(settings, n_envs=n_envs - n_scen, seed=seed, driver=driver)
        w.time_limit[:] = settings.time_limit_s
        worlds.append(w)
    if n_scen and map_pool is not None:
        worlds += map_pool.build(map_pool.draw(map_rng), seed)
    elif n_scen:
        groups: dict[str, list] = {}
        families: dict[str, list[str]] = {}
        for f, family in scenario_sources(settings.scenarios, "train"):
            sc = load_scenario(f)
            groups.setdefault(sc.world_key, []).append(sc)
            families.setdefault(sc.world_key, []).append(family)
        total = sum(len(g) for g in groups.values())
        sizes = {k: max(1, int(round(n_scen * len(g) / total))) for k, g in groups.items()}
        last = list(sizes)[-1]
        sizes[last] = max(1, n_scen - sum(v for k, v in sizes.items() if k != last))
        for k, (name, scs) in enumerate(groups.items()):
            w = FastWorld(n_envs=sizes[name], scenarios=scs, car=env_car(settings),
                          control_period=settings.control_period_s,
                          seed=None if seed is None else seed + 7919 * (k + 1),
                          parallel=settings.parallel)
            w.scenario_families = families[name]  # the curriculum's grouping (training/vec_env.py)
            worlds.append(w)
    return worlds


def make_world(settings: EnvConfig, n_envs: int = 1, seed: int | None = None, driver=None):
    """The backend world of ``settings`` (fast: a FastWorld of n_envs worlds; bullet: a
    BulletWorld on the racetrack); both implement racecav.sim.contract.World.

    :param driver: a traffic driver object or policy callable overriding ``settings.driver``.
    """
    driver = settings.driver if driver is None else driver
    scale = settings.agent_speed_scale
    if scale is None and settings.n_obstacles == 0:
        scale = 1.0  # the racing stage drives at the obstacle cars' speed
    if settings.backend == "fast":
        from racecav.sim.fast_world import FastWorld

        if settings.lidar != "paper" and settings.n_obstacles and isinstance(driver, str) and driver.startswith("policy:"):
            raise ValueError("lidar: a policy traffic driver sees the paper's scan; train the wide view with driver centerline")
        return FastWorld(n_envs=n_envs, world=settings.world, car=env_car(settings),
                         n_obstacles=settings.n_obstacles, heading=settings.heading, driver=driver,
                         agent_speed_scale=scale, control_period=settings.control_period_s,
                         seed=seed, parallel=settings.parallel)
    from racecav.sim.bullet_world import BulletWorld

    if n_envs != 1:
        raise ValueError("backend: the bullet backend runs one world per env")
    if settings.world != "racetrack":
        raise ValueError(f"world: the bullet overtaking env runs on the racetrack (got {settings.world!r})")
    car = env_car(settings)
    return BulletWorld("racetrack", car=car, traffic_driver=driver, heading=settings.heading,
                       n_obstacles=settings.n_obstacles, seed=seed or 0, agent_speed_scale=scale)


class BulletScenarios:
    """Scenario episodes on the PyBullet backend: each reset draws a scenario file and runs it in
    a BulletWorld (rebuilt when the file changes); the world contract passes through."""

    def __init__(self, scenarios: list, car, seed: int | None = None):
        self.scenarios, self.car = scenarios, car
        self.rng = np.random.default_rng(seed)
        self.bw = None
        self.spec = car.lidar
        self.control_period = car.control_period_s
        self.time_limit = np.full(1, np.inf)

    def seed(self, seed: int | None) -> None:
        self.rng = np.random.default_rng(seed)

    def reset(self, seed: int | None = None, options: dict | None = None) -> np.ndarray:
        from racecav.sim.bullet_world import BulletWorld

        if seed is not None:
            self.seed(seed)
        sc = self.scenarios[int(self.rng.integers(len(self.scenarios)))]
        if self.bw is None or self.bw.scenario is not sc:
            if self.bw is not None:
                self.bw.close()
            self.bw = BulletWorld(sc, car=self.car)
        self.time_limit[0] = sc.duration_s
        return self.bw.reset(seed=int(self.rng.integers(2**31 - 1)), options=options)

    def step(self, actions, brake=None):
        return self.bw.step(np.asarray(actions, dtype=np.float64).reshape(1, 2), brake=brake)

    @property
    def time(self) -> np.ndarray:
        return self.bw.time

    def agent_state(self) -> np.ndarray:
        return self.bw.agent_state()

    def success(self) -> np.ndarray:
        return self.bw.success()

    def progress(self) -> np.ndarray:
        return self.bw.progress()

    def close(self) -> None:
        if self.bw is not None:
            self.bw.close()


class OvertakeEnv(gym.Env):
    """One overtaking (or racing, with ``n_obstacles=0``) episode on the racetrack, or one
    scenario episode (``scenarios``: a conflict suite's train split, a folder or a file).

    :param backend: "fast" or "bullet".
    :param heading: "default" (with traffic) or "reversed" (against it).
    :param n_obstacles: obstacle cars (0..15; 0 = the racing stage).
    :param driver: traffic driver ("centerline", "policy:PATH", or a TrafficDriver/callable).
    :param control_period: seconds per step (default: the car's, 0.1 s).
    :param time_limit: episode time limit in seconds (truncation; scenario episodes: their duration).
    :param scenarios: scenario episodes instead of traffic (each reset draws a file).
    :param obs_stack: scans per observation, newest first.
    :param brake_below: the brake action (a_T below it brakes); None: the paper's action.
    :param config: an EnvConfig to start from (keyword arguments override it).
    """

    metadata = {"render_modes": []}

    def __init__(self, backend: str | None = None, heading: str | None = None,
                 n_obstacles: int | None = None, driver=None, control_period: float | None = None,
                 time_limit: float | None = None, world: str | None = None, car: str | None = None,
                 agent_speed_scale: float | None = None, scenarios: str | None = None,
                 obs_stack: int | None = None, brake_below: float | None = None, config: EnvConfig | None = None):
        drv_obj = driver if driver is not None and not isinstance(driver, str) else None
        self.settings = env_settings(config, backend=backend, heading=heading,
                                     n_obstacles=n_obstacles,
                                     driver=driver if isinstance(driver, str) else None,
                                     control_period_s=control_period, time_limit_s=time_limit,
                                     world=world, car=car, agent_speed_scale=agent_speed_scale,
                                     scenarios=scenarios, obs_stack=obs_stack,
                                     scenario_share=1.0 if scenarios else None, brake_below=brake_below)
        st = self.settings
        for term in ("flow_reward",):
            if getattr(st, term):
                raise ValueError(f"{term}: a reward term of the training VecEnv only (training/vec_env.FastVecEnv, "
                                 "--preset fast); this env keeps the paper's reward")
        if st.scenarios and st.backend == "bullet":
            from racecav.common.scenario import load_scenario, scenario_files

            self.worlds = [BulletScenarios([load_scenario(f) for f in scenario_files(st.scenarios, "train")],
                                           env_car(st))]
            self.weights = np.ones(1)
        elif st.scenarios:  # one fast world per world geometry, drawn by their number of files
            self.worlds = make_worlds(st, n_envs=1, driver=drv_obj)
            self.weights = np.array([len(w.scenarios) for w in self.worlds], float)
        else:
            self.worlds = [make_world(st, n_envs=1, driver=drv_obj)]
            self.weights = np.ones(1)
        self.weights /= self.weights.sum()
        self.world = self.worlds[0]
        spec = self.world.spec
        self.n_stack = st.obs_stack
        self.observation_space = gym.spaces.Box(spec.range_min, spec.range_max, (self.n_stack * spec.n_rays,),
                                                np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.dt = self.world.control_period
        self.max_steps = int(round(st.time_limit_s / self.dt))
        self._steps = 0
        self._a_prev = 0.0
        self._stack = None

    def _observe(self, obs: np.ndarray, fresh: bool) -> np.ndarray:
        from racecav.common.policy import ScanStack

        if self._stack is None or fresh:
            self._stack = ScanStack(self.n_stack, self.settings.obs_stride)
        return self._stack(obs).copy()

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        if len(self.worlds) > 1:
            self.world = self.worlds[int(self.np_random.choice(len(self.worlds), p=self.weights))]
        self.world.seed(int(self.np_random.integers(2**63 - 1)))
        obs = self.world.reset(options=options)
        self._steps = 0
        self._a_prev = 0.0
        return self._observe(obs[0], fresh=True), {}

    def step(self, action):
        a = np.asarray(action, dtype=np.float64).reshape(1, 2)
        p0 = self._progress()
        obs, (throttle, a_delta), collided, info = self.world.step(
            a, brake=brake_from_action(a[:, 0], self.settings.brake_below))
        r = (float(reward(throttle, self._a_prev, a_delta)[0])
             + self.settings.progress_reward * (self._progress() - p0))
        self._a_prev = float(a_delta[0])
        self._steps += 1
        terminated = bool(collided[0])
        scenario = bool(self.settings.scenarios)
        if scenario:
            truncated = (not terminated) and bool(self.world.time[0] >= self.world.time_limit[0] - 1e-9)
        else:
            truncated = (not terminated) and self._steps >= self.max_steps
        x, y, yaw, v = self.world.agent_state()[0]
        out = {"x": float(x), "y": float(y), "yaw": float(yaw), "v": float(v)}
        if "wall" in info:
            out.update(contact_wall=bool(info["wall"][0]), contact_car=int(info["car"][0]))
        if scenario and (terminated or truncated):
            out["is_success"] = bool(self.world.success()[0])
        return self._observe(obs[0], fresh=False), r, terminated, truncated, out

    def _progress(self) -> float:
        return float(self.world.progress()[0]) if self.settings.progress_reward else 0.0

    def close(self):
        for w in self.worlds:
            close = getattr(w, "close", None)
            if close:
                close()
