"""``racecav baseline``: the MPC-APF baseline as a controller on the bus.

Same keys, rules and message as ``racecav policy`` (:mod:`racecav.services.controller`): newest
Scan in, one DriveCommand per usable scan out (``source = "baseline"``). Per scan:

1. ego state at the scan's time (:mod:`.ego`: state key when fresh, else dead reckoning of the
   controller's own commands through the car model);
2. obstacles and boundary points from the same lidar scan (:mod:`.perception`), or, in oracle
   mode (diagnosis only), ground-truth ObstacleStates from the simulator;
3. the MPC-APF (:mod:`.mpc`) in the ego frame; its first input is the command.

The lane reference is the line through the ego's pose at the start of an episode, along its
heading (the scenarios drive straight through the crossing; there is no map). An episode starts
at the first scan, when scan stamps jump back or by more than a second, when no scan came for a
second of wall time, or when the state key's pose jumps (the simulator reset the car).

The status ``info`` reports per step: solver iterations, solve time, success, and over the last
200 steps the median/p99 solve time and mean iterations; tracked obstacles; ego source.
"""

from __future__ import annotations

import argparse
import math
import time
from collections import deque
from typing import Any

import numpy as np

from racecav.common import keys
from racecav.common.config import BaselineConfig, Config, apply_options
from racecav.common.messages import ObstacleStates, Scan, VehicleState
from racecav.common.vehicle import CarParams, load_car
from racecav.services.controller import ControllerService


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--oracle", action="store_true",
                   help="take obstacles from the simulator's ground truth (diagnosis only)")
    p.add_argument("--ego-state", choices=["auto", "state", "model"], help="default: baseline.ego_state")
    p.add_argument("--solver", choices=["sqp", "ipopt"], help="default: baseline.solver")
    p.add_argument("--max-scan-age", type=float, help="seconds (default: baseline.max_scan_age_s)")
    p.add_argument("--v-ref", type=float, help="target speed, m/s (default: baseline.v_ref)")


def _rot(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s], [s, c]])


class MpcApfController:
    """The baseline's logic without the bus: scan (+ optional state / ground truth) -> action.

    :param car: car parameters.
    :param cfg: baseline configuration.
    """

    def __init__(self, car: CarParams, cfg: BaselineConfig):
        from racecav.services.baseline.ego import EgoEstimator
        from racecav.services.baseline.mpc import MpcApf
        from racecav.services.baseline.perception import Perception

        self.car, self.cfg = car, cfg
        self.ego = EgoEstimator(car, cfg.ego_state, cfg.initial_speed, cfg.max_state_age_s, cfg.speed_scale)
        self.perception = Perception(car, cfg.perception)
        self.mpc = MpcApf(car, cfg)
        self.last_stamp_ns: int | None = None
        self.last_wall = 0.0
        self.lane = (0.0, 0.0, 0.0)
        self.episodes = 0
        self.last: dict[str, Any] = {}
        self.solve_ms: deque = deque(maxlen=200)
        self.iters: deque = deque(maxlen=200)
        self.failures = 0

    def _new_episode(self) -> None:
        self.perception.reset()
        self.mpc.reset()
        self.ego.reset()
        self.episodes += 1
        self._anchor = True

    def _episode_boundary(self, scan: Scan, state: VehicleState | None) -> bool:
        if self.last_stamp_ns is None:
            return True
        dt = (scan.stamp_ns - self.last_stamp_ns) * 1e-9
        if dt < 0 or dt > 1.0 or time.monotonic() - self.last_wall > 1.0:
            return True
        if state is not None and self.ego.source == "state":
            return math.hypot(state.x - self.ego.x, state.y - self.ego.y) > 0.5
        return False

    def act(self, scan: Scan, state: VehicleState | None = None, state_arrival_ns: int = 0,
            truth: ObstacleStates | None = None, ranges: np.ndarray | None = None) -> tuple[float, float]:
        """Normalised action (a_T, a_delta) for ``scan``.

        :param state: newest VehicleState (or None), with its monotonic arrival time.
        :param truth: ground-truth obstacles (oracle mode) or None (lidar).
        :param ranges: the baseline's view of a wider scan (ControllerService.view); None: the
            scan's ranges.
        """
        if self._episode_boundary(scan, state):
            self._new_episode()
        self.last_stamp_ns, self.last_wall = scan.stamp_ns, time.monotonic()
        x, y, yaw, v, delta = self.ego.estimate(scan.stamp_ns, state, state_arrival_ns)
        if self._anchor:
            self.lane, self._anchor = (x, y, yaw), False
        pose = (x, y, yaw)
        percept = self.perception.update(scan.ranges if ranges is None else ranges, pose, scan.stamp_ns * 1e-9)
        # everything into the ego frame (ego at the origin, heading 0)
        R = _rot(-yaw)
        origin = np.array([x, y])
        obstacles = []
        half = self.car.length / 2 - self.car.width / 2
        if truth is not None:
            dt_truth = (scan.stamp_ns - truth.stamp_ns) * 1e-9
            src = [(o.x + o.speed * math.cos(o.yaw) * dt_truth, o.y + o.speed * math.sin(o.yaw) * dt_truth,
                    o.speed * math.cos(o.yaw), o.speed * math.sin(o.yaw), o.yaw, half) for o in truth.obstacles]
            src.sort(key=lambda o: math.hypot(o[0] - x, o[1] - y))
            src = [o for o in src if math.hypot(o[0] - x, o[1] - y) < self.cfg.perception.max_range]
        else:
            src = []
            for tr in percept.obstacles:
                moving = tr.speed > 0.3
                src.append((tr.x, tr.y, tr.vx, tr.vy, math.atan2(tr.vy, tr.vx) if moving else 0.0,
                            half if moving else 0.0))
        for ox, oy, vx, vy, hd, hl in src:
            px, py = R @ (np.array([ox, oy]) - origin)
            vvx, vvy = R @ np.array([vx, vy])
            obstacles.append((px, py, vvx, vvy, hd - yaw, hl))
        bnd = (percept.boundary - origin) @ R.T if len(percept.boundary) else np.zeros((0, 2))
        lx, ly = R @ (np.array(self.lane[:2]) - origin)
        lane = (lx, ly, self.lane[2] - yaw)
        p = self.mpc.params((0.0, 0.0, 0.0, v, delta), lane, self.cfg.v_ref, obstacles, bnd, percept.weight)
        # several initial guesses only when something is near: free driving stays cheap
        near = bool(obstacles) or (len(bnd) and float(np.min(np.hypot(bnd[:, 0], bnd[:, 1]))) < self.cfg.multi_start_range)
        res = self.mpc.solve(p, multi_start=self.cfg.multi_start and near)
        self.ego.command(res.throttle, res.steer_cmd)
        self.solve_ms.append(res.solve_s * 1e3)
        self.iters.append(res.iterations)
        self.failures += not res.success
        self.last = {"iterations": res.iterations, "solve_ms": round(res.solve_s * 1e3, 3), "flops": res.flops,
                     "success": res.success, "status": res.status, "cost": round(res.cost, 4),
                     "multi_start": bool(self.cfg.multi_start and near), "best_start": self.mpc.last_start,
                     "obstacles": len(obstacles), "tracks": len(self.perception.tracks),
                     "boundary_points": int(min(len(bnd), self.cfg.max_boundary_points)),
                     "ego_source": self.ego.source, "ego_speed": round(v, 3), "steer": round(delta, 4)}
        return res.throttle, res.steer_cmd / self.car.steer_gain

    def stats(self) -> dict[str, Any]:
        s = np.asarray(self.solve_ms) if self.solve_ms else np.zeros(1)
        return {**self.last, "solve_ms_median": round(float(np.median(s)), 3),
                "solve_ms_p99": round(float(np.percentile(s, 99)), 3),
                "iterations_mean": round(float(np.mean(self.iters)) if self.iters else 0.0, 2),
                "solver_failures": self.failures, "episodes": self.episodes,
                "compiled": self.mpc.compiled, "compile_error": self.mpc.compile_error}


class BaselineService(ControllerService):
    """The baseline controller on the bus (see the module docstring)."""

    def __init__(self, cfg: Config):
        bcfg = cfg.baseline
        car = load_car(bcfg.car)
        super().__init__(cfg, "baseline", car, bcfg.max_scan_age_s)
        self.bcfg = bcfg
        self.ctl = MpcApfController(car, bcfg)

    def setup(self) -> None:
        super().setup()
        # side inputs: only the newest matters and it is read, not consumed (no drop counting)
        self._latest: dict[str, tuple] = {"state": (None, 0), "truth": (None, 0)}

        def keep(name):
            return lambda msg: self._latest.__setitem__(name, (msg, time.monotonic_ns()))

        if self.bcfg.ego_state != "model":
            self.subscribe(self.topic(keys.STATE), VehicleState, keep("state"))
        if self.bcfg.obstacles == "oracle":
            self.subscribe(self.topic(keys.OBSTACLES), ObstacleStates, keep("truth"))

    def act(self, scan: Scan) -> tuple[float, float] | None:
        state, arrival = self._latest["state"]
        truth = self._latest["truth"][0]
        if self.bcfg.obstacles == "oracle" and truth is None:
            return None  # oracle mode without ground truth: no command (counted as no_action)
        return self.ctl.act(scan, state, arrival, truth, ranges=self.view(scan))

    def info(self) -> dict[str, Any]:
        return {**super().info(), "obstacle_source": self.bcfg.obstacles, "solver": self.bcfg.solver,
                **self.ctl.stats()}


OPTIONS = {"ego_state": "ego_state", "solver": "solver", "max_scan_age": "max_scan_age_s", "v_ref": "v_ref"}
"""Typed options -> baseline.<field> (validated as the config is: a bad one exits 2 naming both)."""
SECTION = "baseline"


def run(args: argparse.Namespace, cfg: Config) -> int:
    cfg = apply_options(cfg, SECTION, args, OPTIONS,
                        {"obstacles": "oracle"} if getattr(args, "oracle", False) else None)
    try:
        svc = BaselineService(cfg)
    except ValueError as e:
        print(f"racecav baseline: {e}")
        return 2
    return svc.run()
