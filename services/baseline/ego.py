"""The ego state the MPC starts from: pose, speed and actual steering angle at a scan's time.

The car knows what it commanded; it does not necessarily know where it is. Two sources:

- the state key (``VehicleState``: the simulator, or odometry on a car that has it), used while
  fresh (``max_state_age_s`` wall clock) and propagated from its stamp to the scan's stamp;
- the car model driven by the controller's own commands (dead reckoning): the throttle friction
  model of the car file gives the wheel speed, the servo slew limit and the fitted steering lag
  give the steering angle, the kinematic bicycle with the fitted effective wheelbase gives the
  pose. It starts from ``initial_speed`` at the pose (0, 0, 0) of an "odom" frame.

``ego_state = "auto"`` takes the state key when fresh and the model otherwise (re-synchronised to
every state it gets); "state" and "model" force one source (with "state" and no fresh state the
model still fills in, and the status reports it).
"""

from __future__ import annotations

import math
import time

from racecav.common.messages import VehicleState
from racecav.common.vehicle import CarParams, steer_rate_limit, wheel_speed_step



MAX_GAP_S = 1.0
"""Longest stretch (s) the dead-reckoning model integrates between two stamps (ten scans)."""

class EgoEstimator:
    """Ego pose/speed/steering at scan times (see the module docstring).

    :param car: car parameters.
    :param mode: "auto" | "state" | "model".
    :param initial_speed: model start speed (m/s).
    :param max_state_age_s: a VehicleState older than this (wall clock) is not used.
    :param speed_scale: body speed per wheel speed x radius (None: car.agent_speed_scale).
    """

    def __init__(self, car: CarParams, mode: str = "auto", initial_speed: float = 1.0,
                 max_state_age_s: float = 0.3, speed_scale: float | None = None):
        self.car, self.mode, self.initial_speed = car, mode, initial_speed
        # body speed = speed_scale * wheel_radius * w (the ego is the agent: car.agent_speed_scale)
        self.r_eff = car.wheel_radius * (car.agent_speed_scale if speed_scale is None else speed_scale)
        self.max_state_age_ns = int(max_state_age_s * 1e9)
        bic = car.bicycle
        self.wheelbase = bic.lf + bic.lr if bic.fitted else car.wheelbase
        self.steer_tau = bic.steer_tau
        self.reset()

    def reset(self, x: float = 0.0, y: float = 0.0, yaw: float = 0.0, v: float | None = None) -> None:
        v = self.initial_speed if v is None else v
        self.x, self.y, self.yaw = x, y, yaw
        self.w = v / self.r_eff                # friction-model wheel speed
        self.steer = 0.0                       # actual steering angle
        self.steer_servo = 0.0                 # rate-limited servo target (before the lag)
        self.throttle = 0.0                    # last commanded throttle and steering angle
        self.steer_cmd = 0.0
        self.t_ns: int | None = None
        self.source = "model"

    @property
    def v(self) -> float:
        return self.w * self.r_eff

    def command(self, throttle: float, steering_angle: float) -> None:
        """The command just published (it drives the model from now on)."""
        self.throttle, self.steer_cmd = throttle, steering_angle

    def _propagate(self, dt: float) -> None:
        """Advance the model by ``dt`` s with the held command (physics-step substeps)."""
        car = self.car
        n = max(1, int(math.ceil(dt / car.physics_dt - 1e-9)))
        h = dt / n
        for _ in range(n):
            self.w = float(wheel_speed_step(self.w, self.throttle, h, car))
            self.steer_servo = float(steer_rate_limit(self.steer_servo, self.steer_cmd, h, car))
            if self.steer_tau > 0:
                self.steer += (self.steer_servo - self.steer) * (1 - math.exp(-h / self.steer_tau))
            else:
                self.steer = self.steer_servo
            v = self.v
            self.x += h * v * math.cos(self.yaw)
            self.y += h * v * math.sin(self.yaw)
            self.yaw += h * v * math.tan(self.steer) / self.wheelbase

    def estimate(self, scan_stamp_ns: int, state: VehicleState | None = None,
                 state_arrival_ns: int = 0) -> tuple[float, float, float, float, float]:
        """(x, y, yaw, v, steering angle) at the scan's stamp.

        :param state: the newest VehicleState (or None); used when fresh and the mode allows.
        :param state_arrival_ns: its monotonic arrival time.
        """
        fresh = (state is not None and self.mode != "model"
                 and time.monotonic_ns() - state_arrival_ns <= self.max_state_age_ns
                 and 0 <= scan_stamp_ns - state.stamp_ns <= 5e8)
        if fresh:
            self.x, self.y, self.yaw = state.x, state.y, state.yaw
            self.w = max(state.vx, 0.0) / self.r_eff
            # the state reports the servo's rate-limited angle; the wheels follow it with the
            # fitted lag, which the model keeps integrating
            self.steer_servo = state.steering_angle
            self.t_ns = state.stamp_ns
            self.source = "state"
        else:
            self.source = "model"
        if self.t_ns is not None and scan_stamp_ns > self.t_ns:
            # A gap beyond MAX_GAP_S (a restarted simulator, a clock jump, a hostile stamp of
            # 2^63 ns) is not integrated step by step, which would take the process hours: the
            # model coasts through at most MAX_GAP_S and its clock jumps.
            self._propagate(min((scan_stamp_ns - self.t_ns) * 1e-9, MAX_GAP_S))
        self.t_ns = scan_stamp_ns
        return self.x, self.y, self.yaw, self.v, self.steer
