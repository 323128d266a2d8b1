"""FastWorld: N worlds stepped together (numba), the training backend.

Each world holds the agent (car 0) and up to 15 obstacle cars: traffic lapping a loop world under
a pluggable driver (racecav.sim.traffic), or the kinematic actors of scenario files
(racecav.sim.actors); every car can have the 170-ray lidar. Geometry comes from :class:`racecav.common.world.World`
(``walls``, ``centerline``, ``lane_width``, ``wall_thickness``), the car from
:class:`racecav.common.vehicle.CarParams` (box, actuation, fitted single-track model ``bicycle``)
and the lidar from its :class:`racecav.common.lidar.LidarSpec`: nothing is copied here.

Actuation per control step, as in the PyBullet backend: the action is mapped by the shared
``throttle_from_action`` / ``steer_from_action``; over ``physics_substeps`` substeps the wheel
speed follows the shared ``wheel_speed_step`` (AutoVRL friction model) and the steering the shared
``steer_rate_limit``; the kernel integrates the fitted kinematic single-track model and checks
contacts after every substep; the lidar is taken once at the end of the control step.

It implements the world contract (:class:`racecav.sim.contract.World`), as the PyBullet backend
does with one world.
"""

from __future__ import annotations

import math

import numpy as np

from racecav.common import lidar as lidar_mod
from racecav.common import perturb as P
from racecav.common import vehicle as vehicle_mod
from racecav.sim import fast_kernels as K
from racecav.sim.progress import CENTERLINE_DS, LoopProgress, dense_centerline  # noqa: F401 (re-exported)
from racecav.sim.traffic import make_driver

RESPAWN_TRIES = 24
RESPAWN_MIN_DIST = 2.5  # m from every other car when an obstacle car is respawned ...
RESPAWN_MIN_DIST_AGENT = 6.0  # ... and from the agent (over 2 s at its top speed)
RESET_YAW_NOISE = 0.1  # rad, +- around the centerline direction at a reset
OBSTACLE_SPEED_FRACTION = (0.55, 1.0)  # each obstacle car's cruise speed / top speed, uniform
GRAVITY = 9.81
WALLS_PER_CHUNK = 4
V_KIN = 0.3  # m/s: below this speed the single-track model is kinematic (tyre model singular)


class FastWorld:
    """N racetrack worlds with an agent and obstacle cars each, stepped in one numba call chain.

    :param n_envs: number of worlds N.
    :param world: World object or name (common/data/worlds/NAME.toml).
    :param car: CarParams or name.
    :param n_obstacles: obstacle cars per world (0..15; 0 = the racing stage).
    :param heading: "default" (agent with traffic) or "reversed" (against it).
    :param driver: traffic driver: "centerline", a TrafficDriver or a policy callable.
    :param obstacle_lidar: compute the obstacle cars' scans every step (default: if the driver
        needs them). The agent's scan is always computed.
    :param agent_speed_scale: override of car.agent_speed_scale (1.0 for the racing stage).
    :param control_period: override of car.control_period_s (s).
    :param physics_substeps: override of car.physics_substeps.
    :param seed: seed of the reset randomisation.
    :param parallel: spread the lidar over numba's threads (helps when a core is free: 1.5x
        measured on the 2-core machine under load; contention when several runs share the cores).
    :param perturb: sim-to-real perturbations of the agents (a PerturbConfig or its text;
        common/perturb.py): scan, car, floor friction (braking at friction x the fitted
        deceleration, sideways acceleration capped at friction x g below 1), steering offset and
        the delay of their actions (applied at the first substep after it).
    """

    def __init__(self, n_envs: int = 1, world="racetrack", car="slash", n_obstacles: int = 15,
                 heading: str = "default", driver="centerline", obstacle_lidar: bool | None = None,
                 agent_speed_scale: float | None = None, control_period: float | None = None,
                 physics_substeps: int | None = None, seed: int | None = None,
                 parallel: bool = False, scenarios=None, perturb=None):
        self.scenarios = list(scenarios or [])
        if self.scenarios:
            # scenario episodes: the ego and the scenario's kinematic actors (sim/actors.py)
            worlds = {sc.world_key for sc in self.scenarios}
            if len(worlds) != 1:
                raise ValueError(f"scenarios: one world per FastWorld, got {sorted(worlds)}")
            if any(sc.traffic is not None or sc.ego is None for sc in self.scenarios):
                raise ValueError("scenarios: only scenarios with an [ego] and [[obstacles]] (no [traffic])")
            world = self.scenarios[0].build_world()
            n_obstacles = max(1, max(len(sc.obstacles) for sc in self.scenarios))
            driver = None
        if isinstance(world, str):
            from racecav.common.world import load_world

            world = load_world(world)
        if isinstance(car, str):
            car = vehicle_mod.load_car(car)
        self.perturb = P.make(perturb)
        car = P.perturbed_car(car, self.perturb)
        if heading not in ("default", "reversed"):
            raise ValueError(f"heading: expected 'default' or 'reversed', got {heading!r}")
        if not 0 <= n_obstacles <= 15:
            raise ValueError(f"n_obstacles: expected 0..15, got {n_obstacles}")
        self.world, self.car, self.spec = world, car, car.lidar
        self.n_envs = N = int(n_envs)
        self.n_obstacles = n_obstacles
        self.n_cars = C = 1 + n_obstacles
        self.heading = heading
        self.driver = make_driver(driver, backend="fast")
        self.obstacle_lidar = self.driver.needs_lidar if obstacle_lidar is None else obstacle_lidar
        self.agent_speed_scale = car.agent_speed_scale if agent_speed_scale is None else agent_speed_scale
        self.control_period = car.control_period_s if control_period is None else float(control_period)
        self.substeps = car.physics_substeps if physics_substeps is None else int(physics_substeps)
        self.dt = self.control_period / self.substeps
        self._lidar = K.lidar_parallel if parallel else K.lidar

        self.walls = np.ascontiguousarray(world.walls, dtype=np.float64)
        self.wall_box = np.stack([np.minimum(self.walls[:, 0], self.walls[:, 2]),
                                  np.minimum(self.walls[:, 1], self.walls[:, 3]),
                                  np.maximum(self.walls[:, 0], self.walls[:, 2]),
                                  np.maximum(self.walls[:, 1], self.walls[:, 3])], axis=1)
        self.wall_r = 0.5 * float(world.wall_thickness)
        # wall boxes as the PyBullet backend builds them: extended by half a thickness at both
        # ends (no gaps at the joints of bends)
        self.faces = K.wall_faces(self.walls, self.wall_r, extend=self.wall_r)
        # 4 walls (16 faces) per culling chunk: measured fastest of 2/4/8 on the racetrack
        self.chunks = K.face_chunks(self.faces, 4 * WALLS_PER_CHUNK)
        # worlds without a centerline (intersection, open floor): no traffic, no random resets
        self.cl = dense_centerline(world) if world.centerline is not None else np.zeros((1, 4))
        if world.centerline is None and n_obstacles and not self.scenarios:
            raise ValueError(f"n_obstacles: world {world.name!r} has no centerline for traffic")
        self.cl_ds = float(np.hypot(*(self.cl[1, :2] - self.cl[0, :2]))) if len(self.cl) > 1 else 1.0
        self.lat_max = max(0.0, 0.5 * float(world.lane_width) - 0.5 * car.width - 0.15)
        self.hx, self.hy = 0.5 * car.length, 0.5 * car.width
        m = car.lidar_mount
        self.mount = np.array([m.x, m.y, m.yaw], dtype=np.float64)
        ang = lidar_mod.ray_angles(self.spec).astype(np.float64)
        if np.abs(ang + self.mount[2]).max() >= math.pi / 2:
            raise ValueError("lidar: the fast world's lidar needs every ray within +-90 deg of ahead")
        self.ray_c, self.ray_s, self.ray_t = np.cos(ang), np.sin(ang), np.tan(ang)
        b = car.bicycle
        self.set_bicycle(b)

        f = np.zeros
        self.x, self.y, self.yaw = f((N, C)), f((N, C)), f((N, C))
        self.v, self.w, self.delta, self.delta_cmd = f((N, C)), f((N, C)), f((N, C)), f((N, C))
        self.skid = np.zeros((N, C), bool)  # braking agents (their wheels slide)
        self.beta, self.r = f((N, C)), f((N, C))  # slip angle and yaw rate of the single-track model
        self.active = np.ones((N, C), dtype=bool)
        self.track = LoopProgress(self.cl, (N, C))  # every car's centerline station (traffic, progress)
        self.cl_idx = self.track.idx
        self.lane_offset, self.vfac = f((N, C)), f((N, C))
        self.speed_scale = np.ones((N, C))
        self.speed_scale[:, 0] = self.agent_speed_scale
        self.corners = f((N, C, 4, 2))
        self.ranges = np.full((N, C, self.spec.n_rays), np.inf, dtype=np.float32)
        self.observe = np.zeros((N, C), dtype=bool)
        self.observe[:, 0] = True
        self.observe[:, 1:] = self.obstacle_lidar
        # contacts: the agent after every substep (it ends the episode), the obstacle cars once
        # per control step (a touch only respawns them)
        self.check_all = np.ones((N, C), dtype=bool)
        self.check_agent = np.zeros((N, C), dtype=bool)
        self.check_agent[:, 0] = True
        self.wall_hit = np.zeros((N, C), dtype=bool)
        self.car_hit = np.full((N, C), -1, dtype=np.int64)
        self._traffic_act = f((N, C, 2))
        self.actions = f((N, C, 2))
        self.time = f(N)
        self.respawns = 0
        self.bad_actions = 0  # non-finite agent actions replaced by 0 (counted)
        self.rng = np.random.default_rng(seed)
        self._prng = P.trial_rng(0 if seed is None else seed)
        # the perturbation's state: the agents' scans as they see them, and their recent actions
        # for the delay (newest first)
        self.obs_ranges = self.ranges[:, 0].copy() if self.perturb.active() else None
        self.steer_offset = f(N)
        self.delay = f(N)
        self.jitter = f(N)
        self._hist_a = f((N, 1, 2))
        self._hist_b = np.zeros((N, 1), bool)
        self._hist_d = f((N, 1))
        self._set_perturb_arrays(np.arange(N))
        # progress (m): along the centerline in the agent's direction (traffic), or along the
        # ego's initial heading (scenario episodes)
        self.prog = f(N)
        self.start_pose = f((N, 3))
        self.time_limit = np.full(N, np.inf)   # scenario episodes: each scenario's duration
        self.min_progress = f(N)
        self.scenario_index = np.full(N, -1, dtype=np.int64)
        self.collided = np.zeros(N, dtype=bool)
        self.actors = None
        self.scenario_of_env: np.ndarray | None = None
        """Scenario index per world (validation, evaluation); None: drawn at each reset."""
        self.draw_p: np.ndarray | None = None
        """Draw probability per scenario (a training curriculum); None: uniform."""
        self.scenario_families: list[str] = [sc.name for sc in self.scenarios]
        """The curriculum's group of each scenario (make_worlds sets suite families)."""
        if self.scenarios:
            from racecav.sim.actors import ActorBatch

            self.actors = ActorBatch(N, n_obstacles)
            self.dynamic = np.zeros((N, C), dtype=bool)  # only the ego is integrated
            self.dynamic[:, 0] = True

    def set_bicycle(self, b) -> None:
        """Use single-track parameters ``b`` (BicycleParams or any object with its fields)."""
        self.lf, self.lr, self.iz, self.mu = float(b.lf), float(b.lr), float(b.iz), float(b.mu)
        self.c_sf, self.c_sr = float(b.c_sf), float(b.c_sr)
        self.steer_tau, self.speed_tau = float(b.steer_tau), float(b.speed_tau)
        # the floor's friction (perturb): the fitted tyre model is kept; a braking car skids at
        # friction x its fitted deceleration, and below 1 the sideways acceleration is capped at
        # friction x g (PyBullet's Coulomb friction slides there)
        fr = self.perturb.friction
        self.brake_decel = float(b.brake_decel) * fr
        self.a_lat_max = fr * GRAVITY if fr < 1.0 else math.inf
        self.scrub = float(getattr(b, "scrub", 0.0))
        self.scrub_lat = float(getattr(b, "scrub_lat", 0.0))
        self.c_speed_inv, self.heading_c4, self.heading_s4 = b.c_speed_inv, b.heading_c4, b.heading_s4

    # ------------------------------------------------------------------ resets
    def seed(self, seed: int | None) -> None:
        self.rng = np.random.default_rng(seed)
        self._prng = P.trial_rng(0 if seed is None else seed)

    def _set_perturb_arrays(self, envs) -> None:
        """The perturbation's per-world state of ``envs`` (at a restart: the action history cleared)."""
        p = self.perturb
        self.steer_offset[envs] = p.steer_offset_rad
        self.delay[envs] = p.latency_s + p.actuator_delay_s
        self.jitter[envs] = p.scan_jitter_s
        most = float((self.delay + self.jitter).max())
        need = int(math.ceil(most / self.control_period)) + 2 if most > 0 else 1
        if need > self._hist_a.shape[1]:
            N = self.n_envs
            self._hist_a = np.concatenate([self._hist_a, np.zeros((N, need - self._hist_a.shape[1], 2))], 1)
            self._hist_b = np.concatenate([self._hist_b, np.zeros((N, need - self._hist_b.shape[1]), bool)], 1)
            self._hist_d = np.concatenate([self._hist_d, np.zeros((N, need - self._hist_d.shape[1]))], 1)
        self._hist_a[envs] = 0.0  # before the first action the agent coasts, as the sim's
        self._hist_b[envs] = False
        self._hist_d[envs] = 0.0

    def reset(self, seed: int | None = None, options: dict | None = None) -> np.ndarray:
        """Reset every world. :return: agent observations (N, 170) float32."""
        if seed is not None:
            self.seed(seed)
        self.reset_worlds(np.arange(self.n_envs))
        return self.agent_obs()

    def reset_worlds(self, envs) -> None:
        """Re-place all cars of the worlds ``envs`` (indices or a bool mask) and rescan them."""
        envs = np.flatnonzero(envs) if np.asarray(envs).dtype == bool else np.asarray(envs, dtype=np.int64)
        if envs.size == 0:
            return
        self.prog[envs] = 0.0
        self.collided[envs] = False
        if self.actors is not None:
            self._place_scenarios(envs)
            return
        C = self.x.shape[1]
        u = self.rng.random((envs.size, 1 + 5 * C))
        for i, n in enumerate(envs):
            K.place_world(int(n), self.x, self.y, self.yaw, self.v, self.w, self.delta, self.cl_idx,
                          self.lane_offset, self.vfac, self.active, self.cl, self.cl_ds, u[i],
                          self.n_cars, self.heading == "reversed", self.lat_max, RESET_YAW_NOISE,
                          *OBSTACLE_SPEED_FRACTION)
        self._restart(envs)
        self._scan(envs)

    def _restart(self, envs) -> None:
        """Episode clock, steering command, slip, yaw rate and contact flags of ``envs`` to zero."""
        self._set_perturb_arrays(np.atleast_1d(envs))
        self.delta_cmd[envs] = 0.0
        self.beta[envs] = 0.0
        self.r[envs] = 0.0
        self.time[envs] = 0.0
        self.wall_hit[envs] = False
        self.car_hit[envs] = -1

    def _place_scenarios(self, envs: np.ndarray) -> None:
        """Draw a scenario and a trial for each world of ``envs``; place the ego and actors."""
        for n in envs:
            if self.draw_p is None:
                k = int(self.rng.integers(len(self.scenarios)))
            else:
                k = int(self.rng.choice(len(self.scenarios), p=self.draw_p))
            if self.scenario_of_env is not None:
                k = int(self.scenario_of_env[n])
            self.place_trial(int(n), k, self.scenarios[k].sample(self.rng), rescan=False)
        self._actors_to_cars()
        self._scan(envs)

    def place_trial(self, n: int, k: int, trial, rescan: bool = True) -> None:
        """Start world ``n`` on a concrete trial of scenario ``k`` (parity tests: the trial the
        PyBullet backend drew)."""
        sc = self.scenarios[k]
        ex, ey, eyaw, ev = trial.ego
        self.scenario_index[n] = k
        self.time_limit[n] = sc.duration_s
        self.min_progress[n] = sc.success.min_progress_m
        self.start_pose[n] = ex, ey, eyaw
        self.x[n, 0], self.y[n, 0], self.yaw[n, 0], self.v[n, 0] = ex, ey, eyaw, ev
        self.w[n, 0] = ev / (self.car.wheel_radius * self.speed_scale[n, 0])
        self.actors.load(n, trial.obstacles)
        self.active[n, 1:] = self.actors.used[n]
        self.prog[n] = 0.0
        self.collided[n] = False
        envs = np.array([n])
        self.delta[envs] = 0.0
        self._restart(envs)
        if rescan:
            self._actors_to_cars()
            self._scan(envs)

    def _actors_to_cars(self) -> None:
        a = self.actors
        self.x[:, 1:], self.y[:, 1:], self.yaw[:, 1:], self.v[:, 1:] = a.x, a.y, a.yaw, a.v

    def set_state(self, env: int, car: int = 0, *, x=None, y=None, yaw=None, v=None, w=None,
                  delta=None) -> None:
        """Set one car's state (parity tests, scripted scenes); rescans that world.

        :param v: speed (m/s); the wheel state ``w`` follows it unless given.
        """
        if v is not None and w is None:
            w = v / (self.car.wheel_radius * self.speed_scale[env, car])
        for name, val in (("x", x), ("y", y), ("yaw", yaw), ("v", v), ("w", w), ("delta", delta)):
            if val is not None:
                getattr(self, name)[env, car] = val
        if delta is not None:
            self.delta_cmd[env, car] = delta
        self.beta[env, car] = 0.0
        self.r[env, car] = 0.0
        if x is not None or y is not None:
            self.track.place(env, car, self.x[env, car], self.y[env, car])
        self._scan(np.array([env]))

    def remove_car(self, env: int, car: int) -> None:
        """Take a car out of a world (neither seen nor touched)."""
        self.active[env, car] = False
        self.x[env, car], self.y[env, car] = 1e6 + 10.0 * car, 1e6
        self._scan(np.array([env]))

    # ------------------------------------------------------------------ stepping
    def step(self, actions, brake=None, observe: bool = True) -> tuple[np.ndarray | None, tuple[np.ndarray, np.ndarray], np.ndarray, dict]:
        """Advance every world by one control period.

        :param actions: (N, 2) agent actions (a_T, a_delta), normalised.
        :param brake: (N,) bool or None: these agents brake (wheel speed target 0, as PyBullet's).
        :param observe: False: no scans (obs None; a planner that reads the state, training/expert.py).
        :return: obs (N, 170) float32; reward inputs (T (N,), a_delta clipped to [-1, 1] (N,));
            collided (N,) bool (agent touched a wall or a car during the step); info dict with
            ``wall`` / ``car`` contact flags and the number of obstacle respawns this step.
        """
        a = np.asarray(actions, dtype=np.float64).reshape(self.n_envs, 2)
        if not np.isfinite(a).all():  # a diverged policy must not poison the world's state
            self.bad_actions += int((~np.isfinite(a)).any(axis=1).sum())
            a = np.nan_to_num(a, nan=0.0, posinf=1.0, neginf=-1.0)
        self.actions[:, 0] = a
        if brake is not None:
            brake = np.asarray(brake, bool).reshape(self.n_envs)
        self.skid[:, 0] = False if brake is None else brake
        if self.actors is not None:
            self.actors.control(self.agent_state())
        elif self.n_cars > 1:
            self.actions[:, 1:] = self.driver(self)
        car = self.car
        T = vehicle_mod.throttle_from_action(self.actions[..., 0])
        target = vehicle_mod.steer_from_action(self.actions[..., 1], car)
        delayed = bool(self.delay.any() or self.jitter.any())
        if delayed:  # the agents' actions take effect their delay after their scan (perturb)
            self._hist_a = np.roll(self._hist_a, 1, axis=1)
            self._hist_b = np.roll(self._hist_b, 1, axis=1)
            self._hist_d = np.roll(self._hist_d, 1, axis=1)
            self._hist_a[:, 0] = a
            self._hist_b[:, 0] = False if brake is None else brake
            self._hist_d[:, 0] = self.delay + (self._prng.uniform(0.0, 1.0, self.n_envs) * self.jitter
                                               if self.jitter.any() else 0.0)
            lag = np.arange(self._hist_d.shape[1]) * self.control_period
        if self.steer_offset.any():
            target[:, 0] = np.clip(target[:, 0] + self.steer_offset, car.delta_min, car.delta_max)
        self.wall_hit[:] = False
        self.car_hit[:] = -1
        scenario = self.actors is not None
        dynamic = self.dynamic if scenario else self.active
        for k in range(self.substeps):
            if scenario:  # actors first, as the PyBullet backend moves them before its step
                self.actors.advance(self.dt)
                self._actors_to_cars()
            if delayed:  # the newest action in effect at this substep's start
                due = self._hist_d - lag <= k * self.dt + 1e-9
                j = np.where(due.any(axis=1), due.argmax(axis=1), due.shape[1] - 1)
                rows = np.arange(self.n_envs)
                a_k = self._hist_a[rows, j]
                T[:, 0] = vehicle_mod.throttle_from_action(a_k[:, 0])
                target[:, 0] = np.clip(vehicle_mod.steer_from_action(a_k[:, 1], car) + self.steer_offset,
                                       car.delta_min, car.delta_max)
                brake = self._hist_b[rows, j]
                self.skid[:, 0] = brake
            self.w = vehicle_mod.wheel_speed_step(self.w, T, self.dt, car)
            if brake is not None:  # the wheels' target follows the skidding body down to 0
                scale = car.wheel_radius * self.speed_scale[brake, 0]
                self.w[brake, 0] = np.maximum(self.v[brake, 0] - self.brake_decel * self.dt, 0.0) / scale
            self.delta_cmd = vehicle_mod.steer_rate_limit(self.delta_cmd, target, self.dt, car)
            K.integrate(self.x, self.y, self.yaw, self.v, self.beta, self.r, self.delta,
                        self.delta_cmd, self.w, self.speed_scale, dynamic, self.skid, car.wheel_radius,
                        car.wheelbase, car.mass, GRAVITY, self.lf, self.lr, self.iz, self.mu,
                        self.c_sf, self.c_sr, self.steer_tau, self.speed_tau, self.scrub,
                        self.scrub_lat, V_KIN, self.dt, self.c_speed_inv, self.heading_c4,
                        self.heading_s4, self.a_lat_max)
            K.box_corners(self.x, self.y, self.yaw, self.hx, self.hy, self.corners)
            K.contacts(self.x, self.y, self.yaw, self.active, self.walls, self.wall_box,
                       self.corners, self.hx, self.hy, self.wall_r,
                       self.check_all if k == self.substeps - 1 and not scenario else self.check_agent,
                       self.wall_hit, self.car_hit)
        K.wrap_angles(self.yaw)
        self.time += self.control_period
        collided = self.wall_hit[:, 0] | (self.car_hit[:, 0] >= 0)
        self.collided |= collided
        if scenario:
            respawned = 0
        else:
            respawned = self._respawn_obstacles(collided)
            # every car's centerline station, by a local search (traffic, progress): a global
            # nearest point would jump between the arms of a crossing (figure eight)
            ds = self.track.update(self.x, self.y)
            self.prog += -ds if self.heading == "reversed" else ds
        if observe:
            self._scan_all(self.observe)
        a_d = np.clip(a[:, 1], -1.0, 1.0)
        info = {"wall": self.wall_hit[:, 0].copy(), "car": self.car_hit[:, 0].copy(),
                "respawned": respawned}
        return self.agent_obs() if observe else None, (T[:, 0], a_d), collided, info

    def _respawn_obstacles(self, agent_collided: np.ndarray) -> int:
        """Obstacle cars that touched a wall or another obstacle car reappear elsewhere on the
        track (worlds whose agent collided are reset by the caller anyway)."""
        if self.n_cars == 1:
            return 0
        bad = self.wall_hit[:, 1:] | (self.car_hit[:, 1:] > 0)
        bad &= ~agent_collided[:, None]
        if not bad.any():
            return 0
        ns, cs = np.nonzero(bad)
        u = self.rng.random((ns.size, RESPAWN_TRIES, 2))
        for i in range(ns.size):
            n, c = int(ns[i]), int(cs[i]) + 1
            if not K.respawn_car(n, c, self.x, self.y, self.yaw, self.v, self.w, self.delta,
                                 self.cl_idx, self.lane_offset, self.active, self.cl, u[i],
                                 RESPAWN_MIN_DIST, RESPAWN_MIN_DIST_AGENT, self.lat_max):
                self.active[n, c] = False  # no free spot: the car leaves the world
                self.x[n, c], self.y[n, c] = 1e6 + 10.0 * c, 1e6
            self.delta_cmd[n, c] = self.delta[n, c]
            self.beta[n, c] = self.r[n, c] = 0.0
        K.box_corners(self.x, self.y, self.yaw, self.hx, self.hy, self.corners)
        self.respawns += ns.size
        return int(ns.size)

    def _scan(self, envs: np.ndarray) -> None:
        """Rescan the worlds ``envs`` (after a reset or a set_state)."""
        K.box_corners(self.x, self.y, self.yaw, self.hx, self.hy, self.corners)
        observe = np.zeros_like(self.observe)
        observe[envs] = self.observe[envs]
        self._scan_all(observe)

    def _scan_all(self, observe: np.ndarray) -> None:
        self._lidar(self.x, self.y, self.yaw, self.active, observe, self.faces, self.chunks,
                    self.corners, self.mount, self.ray_c, self.ray_s, self.ray_t,
                    self.spec.angle_min, self.spec.angle_increment, self.spec.range_max,
                    self.ranges)
        if self.obs_ranges is not None:  # the agents' scans as their sensor service publishes them
            for n in np.flatnonzero(observe[:, 0]):
                self.obs_ranges[n] = P.perturb_scan(self.ranges[n, 0], self.spec, self.perturb, self._prng)

    def seen_by_agent(self, envs: np.ndarray, pose: np.ndarray | None = None) -> np.ndarray:
        """(len(envs), C - 1) bool: the other cars that return at least one ray of the agent's
        current scan in the worlds ``envs`` (line of sight past the walls and the other cars).
        Each car is taken out in turn and the agent's scan redone: a car is seen where that
        changes the scan. Costs one agent scan per other car and world.

        :param pose: (len(envs), 3) x, y, yaw to scan from instead of the agent's own pose (the
            agent's box moved there; a counterfactual view, e.g. of an ego that kept its road).
            Costs one more scan. The world is not changed."""
        envs = np.asarray(envs, dtype=np.int64)
        N, C = self.x.shape
        out = np.zeros((len(envs), C - 1), dtype=bool)
        if not len(envs):
            return out
        observe = np.zeros_like(self.observe)
        observe[envs, 0] = True
        x, y, yaw, corners, base = self.x, self.y, self.yaw, self.corners, self.ranges
        if pose is not None:
            x, y, yaw = x.copy(), y.copy(), yaw.copy()
            x[envs, 0], y[envs, 0], yaw[envs, 0] = np.asarray(pose, dtype=np.float64).T
            corners, base = np.empty_like(self.corners), np.empty_like(self.ranges)
            K.box_corners(x, y, yaw, self.hx, self.hy, corners)
            self._lidar(x, y, yaw, self.active, observe, self.faces, self.chunks, corners, self.mount,
                        self.ray_c, self.ray_s, self.ray_t, self.spec.angle_min, self.spec.angle_increment,
                        self.spec.range_max, base)
        ranges = np.empty_like(self.ranges)
        for c in range(1, C):
            active = self.active.copy()
            active[:, c] = False
            self._lidar(x, y, yaw, active, observe, self.faces, self.chunks, corners,
                        self.mount, self.ray_c, self.ray_s, self.ray_t, self.spec.angle_min,
                        self.spec.angle_increment, self.spec.range_max, ranges)
            out[:, c - 1] = (ranges[envs, 0] != base[envs, 0]).any(axis=1) & self.active[envs, c]
        return out

    # ------------------------------------------------------------------ views
    def agent_obs(self) -> np.ndarray:
        """The agents' observations (N, 170): Scan ranges through the shared ``sanitize``."""
        return lidar_mod.sanitize(self.ranges[:, 0] if self.obs_ranges is None else self.obs_ranges, self.spec)

    def observations(self) -> np.ndarray:
        """Every car's observation (N, C, 170) (obstacle scans are current only if
        ``obstacle_lidar``)."""
        return lidar_mod.sanitize(self.ranges, self.spec)

    def agent_state(self) -> np.ndarray:
        """(N, 4) agent x, y, yaw, forward speed v."""
        return np.stack([self.x[:, 0], self.y[:, 0], self.yaw[:, 0], self.v[:, 0]], axis=1)

    def progress(self) -> np.ndarray:
        """(N,) ego progress (m) since the reset: along the centerline in its driving direction
        (traffic episodes, accumulated over laps), else along its initial heading."""
        if self.actors is None:
            return self.prog.copy()
        x0, y0, yaw0 = self.start_pose.T
        return (self.x[:, 0] - x0) * np.cos(yaw0) + (self.y[:, 0] - y0) * np.sin(yaw0)

    def contact(self) -> np.ndarray:
        """(N,) the agent touched something since the reset."""
        return self.collided.copy()

    def success(self) -> np.ndarray:
        """(N,) no contact since the reset and at least the scenario's minimum progress."""
        return ~self.collided & (self.progress() >= self.min_progress)

    def obstacles(self) -> np.ndarray:
        """(N, C-1, 4) x, y, yaw, speed of the obstacle cars (parked slots far away)."""
        return np.stack([self.x[:, 1:], self.y[:, 1:], self.yaw[:, 1:], self.v[:, 1:]], axis=-1)
