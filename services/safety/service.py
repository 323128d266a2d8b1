"""``racecav safety``: the emergency-brake supervisor, a brake input of the actuator's mux.

Every Scan is judged as it arrives (in the subscriber callback: microseconds of numpy) by
:class:`~racecav.services.safety.ttc.BrakeLogic` with the ego speed of
:class:`~racecav.services.baseline.ego.EgoEstimator` (the state key while fresh, else the
controller's commands through the car model, as the MPC-APF baseline does). While it brakes it
publishes one DriveCommand per scan on racecav/<car>/safety (source "safety", throttle 0, the
controller's current steering angle, naming the scan it answers); the mux (actuator and sim)
brakes the motor while that input is fresh and hands back to the inputs below it
``actuator.safety_timeout_s`` after the last one. It never edits the controller's command.

Every judged scan also gets a verdict, JSON ``{"scan_seq", "brake", "ttc_s", "v"}`` on
racecav/<car>/safety/verdict (published after the brake command): monitoring, and the lockstep
simulator's cue that the scan has been judged. Status: brakes, false-brake candidates, scans,
brake scans, the last iTTC and speed, and where the speed came from.
"""

from __future__ import annotations

import argparse
import json
import math
import threading
import time
from typing import Any

import numpy as np

from racecav.common import keys
from racecav.common.bus import Service
from racecav.common.config import Config, apply_options
from racecav.common.messages import INT64_MAX, DriveCommand, Scan, VehicleState
from racecav.common.vehicle import load_car
from racecav.services.baseline.ego import EgoEstimator
from racecav.services.safety.ttc import BrakeLogic


class SafetyService(Service):
    """The supervisor (see the module docstring)."""

    def __init__(self, cfg: Config, name: str = "safety"):
        super().__init__(cfg, name)
        self.scfg = cfg.safety
        self.car_params = load_car(self.scfg.car)
        self.logic = BrakeLogic(self.scfg, self.car_params)
        self.ego = EgoEstimator(self.car_params, self.scfg.ego_state, self.scfg.initial_speed,
                                self.scfg.max_state_age_s)
        self._lock = threading.Lock()
        self._steer = (0.0, 0)         # controller's steering angle and its arrival (monotonic ns)
        self.counts = {"scans": 0, "stale": 0, "commands": 0, "resets": 0}
        self._last_state: tuple[int, float, float] | None = None   # seq, x, y
        self.v = 0.0
        self.last_compute_ns = 0

    def setup(self) -> None:
        self.pub = self.publisher(self.topic(keys.SAFETY), command=True)
        self.verdict = self.session.declare_publisher(keys.service_key(self.car, self.name, "verdict"))
        self._declared.append(self.verdict)
        self.state = self.inbox(self.topic(keys.STATE), VehicleState)
        self.subscribe(self.topic(keys.CMD), DriveCommand, self._on_cmd)
        self.subscribe(self.topic(keys.SCAN), Scan, self._on_scan)

    def _on_cmd(self, cmd: DriveCommand) -> None:
        with self._lock:
            self.counts["commands"] += 1
            # the model follows what the car was told (while braking: no throttle)
            self.ego.command(0.0 if self.logic.braking else cmd.throttle, cmd.steering_angle)
            self._steer = (cmd.steering_angle, time.monotonic_ns())

    def _on_scan(self, scan: Scan) -> None:
        arrival = time.monotonic_ns()
        with self._lock:
            self.judge(scan, arrival)

    def judge(self, scan: Scan, arrival_ns: int) -> bool:
        """Judge one scan; publish the brake command (if braking) and the verdict."""
        t0 = time.perf_counter_ns()
        if scan.source == "real" and arrival_ns - scan.stamp_ns > self.scfg.max_scan_age_s * 1e9:
            self.counts["stale"] += 1
            self._record_error(f"stale scan {scan.seq}: {(arrival_ns - scan.stamp_ns) / 1e6:.1f} ms old")
            return self.logic.braking
        state, state_arrival = self.state.latest()
        if state is not None and (self._last_state is None or state.seq != self._last_state[0]):
            if self._last_state is not None and math.hypot(state.x - self._last_state[1], state.y - self._last_state[2]) \
                    > self.scfg.reset_jump_m:
                self.logic.reset()  # moved (a new episode): no brake carried over
                self.counts["resets"] += 1
            self._last_state = (state.seq, state.x, state.y)
        _, _, _, v, steer = self.ego.estimate(scan.stamp_ns, state, state_arrival)
        self.v = v
        geom = self.logic.geometry(scan.angle_min, scan.angle_increment, scan.ranges.shape[0])
        brake = self.logic.update(geom, scan.ranges, v, scan.stamp_ns * 1e-9, steer)
        self.counts["scans"] += 1
        if brake:
            self.ego.command(0.0, self.ego.steer_cmd)
            steer, at = self._steer
            if arrival_ns - at > self.scfg.steer_timeout_s * 1e9:
                steer = 0.0
            compute = time.perf_counter_ns() - t0
            stamp = time.monotonic_ns() if scan.source == "real" else scan.stamp_ns + compute
            stamp = min(stamp, INT64_MAX)  # a scan stamped at the end of int64 must not overflow ours
            a_steer = float(np.clip(steer / self.car_params.steer_gain, -1.0, 1.0))
            self.pub.put(DriveCommand(stamp_ns=stamp, seq=self.logic.brake_scans, source="safety",
                                      a_throttle=-1.0, a_steer=a_steer, throttle=0.0, steering_angle=steer,
                                      scan_seq=scan.seq, scan_stamp_ns=scan.stamp_ns, compute_ns=compute))
        self.last_compute_ns = time.perf_counter_ns() - t0
        ttc = self.logic.last_ttc
        self.verdict.put(json.dumps({"scan_seq": scan.seq, "brake": brake, "v": round(v, 4),
                                     "ttc_s": round(ttc, 4) if np.isfinite(ttc) else None}).encode())
        return brake

    def step(self) -> None:
        self.stop_event.wait(0.2)  # scans are judged in the callback

    def info(self) -> dict[str, Any]:
        lg = self.logic
        ttc = lg.last_ttc
        return {**self.counts, "braking": lg.braking, "brakes": lg.brakes,
                "false_brake_candidates": lg.false_brake_candidates, "brake_scans": lg.brake_scans,
                "ttc_s": ttc if np.isfinite(ttc) else None, "v": self.v, "speed_source": self.ego.source,
                "threshold_s": self.scfg.threshold_s, "last_compute_us": self.last_compute_ns / 1e3}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--threshold", type=float, help="brake below this iTTC (s); default safety.threshold_s")
    p.add_argument("--debounce", type=int, help="scans in a row below the threshold; default safety.debounce_scans")
    p.add_argument("--ego-state", choices=["auto", "state", "model"], help="ego speed source; default safety.ego_state")


OPTIONS = {"threshold": "threshold_s", "debounce": "debounce_scans", "ego_state": "ego_state"}
"""Typed options -> safety.<field> (validated as the config is: a bad one exits 2 naming both)."""
SECTION = "safety"


def run(args: argparse.Namespace, cfg: Config) -> int:
    return SafetyService(apply_options(cfg, SECTION, args, OPTIONS)).run()
