"""What the actuator sends, decided without I/O: calibration mapping, priority mux, watchdog, e-stop.

Mapping (f1tenth convention, XTENTH calibration by default):
- throttle T in [0, 1] -> speed v (m/s): ``throttle_map = "sim"`` uses the simulator's
  steady-state speed for T, i.e. the wheel speed w solving ``c_quad w^2 + c_lin w = gain T``
  (the car file's friction model at rest) times wheel_radius and agent_speed_scale: what T meant
  to the policy while it learnt (full throttle = 2.7 m/s with the slash defaults). ``"linear"``
  is ``v = T * speed_max_mps``. Then ERPM = speed_to_erpm_gain * v + offset, clipped to erpm_max
  (speed_mode "rpm"); or duty = T * duty_max; or current = T * current_max_a.
- steering angle delta (rad, + left) -> servo = gain * delta + offset, clipped to the servo limits.

Safety, in priority order: a latched e-stop; then a fresh teleop command (it overrides, and
holds the controller off for teleop_hold_s); then a fresh command from the configured
controller; otherwise neutral (brake/zero/coast per config) with the steering centred. "Fresh" is
younger than timeout_s since it arrived; a malformed command on either key discards the command
in force at once. Commands from any other source are refused and counted.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

from racecav.common.config import ActuatorConfig
from racecav.common.messages import DriveCommand
from racecav.services.actuator import vesc_protocol as vp


def sim_steady_speed(throttle: float, car) -> float:
    """Steady-state speed (m/s) of the simulator's throttle model for a constant T (see module doc)."""
    t = min(max(throttle, 0.0), 1.0)
    a, b, g = car.throttle_c_quad, car.throttle_c_lin, car.throttle_gain
    w = (-b + math.sqrt(b * b + 4 * a * g * t)) / (2 * a) if a > 0 else g * t / b
    return w * car.wheel_radius * car.agent_speed_scale


class Mapping:
    """Calibrated command -> VESC frames.

    :param cfg: the actuator section.
    :param car: CarParams (for throttle_map "sim"); may be None for "linear".
    """

    def __init__(self, cfg: ActuatorConfig, car=None):
        self.cfg, self.car = cfg, car
        if cfg.servo_min > cfg.servo_max:
            raise ValueError("actuator.servo_min: must not exceed servo_max")

    def speed(self, throttle: float) -> float:
        if self.cfg.throttle_map == "sim":
            return sim_steady_speed(throttle, self.car)
        return min(max(throttle, 0.0), 1.0) * self.cfg.speed_max_mps

    def erpm(self, throttle: float) -> float:
        e = self.cfg.speed_to_erpm_gain * self.speed(throttle) + self.cfg.speed_to_erpm_offset
        return min(max(e, -self.cfg.erpm_max), self.cfg.erpm_max)

    def servo(self, steering_angle: float) -> float:
        s = self.cfg.steering_angle_to_servo_gain * steering_angle + self.cfg.steering_angle_to_servo_offset
        return min(max(s, self.cfg.servo_min), self.cfg.servo_max)

    def motor_frame(self, throttle: float) -> bytes:
        t = min(max(throttle, 0.0), 1.0)
        if self.cfg.speed_mode == "rpm":
            return vp.set_rpm(self.erpm(t))
        if self.cfg.speed_mode == "duty":
            return vp.set_duty(t * self.cfg.duty_max)
        return vp.set_current(t * self.cfg.current_max_a)

    def drive_frames(self, cmd: DriveCommand) -> list[bytes]:
        return [self.motor_frame(cmd.throttle), vp.set_servo_pos(self.servo(cmd.steering_angle))]

    def neutral_frames(self) -> list[bytes]:
        """Motor stopped per ``neutral`` and steering centred (servo at the calibrated offset)."""
        n = self.cfg.neutral
        motor = vp.set_current_brake(self.cfg.brake_current_a) if n == "brake" else \
            vp.set_rpm(0) if n == "rpm0" else vp.set_current(0)
        centre = min(max(self.cfg.steering_angle_to_servo_offset, self.cfg.servo_min), self.cfg.servo_max)
        return [motor, vp.set_servo_pos(centre)]


@dataclass
class Decision:
    cmd: DriveCommand | None
    """The command to apply, or None for neutral."""
    reason: str
    """Who drives ("controller", "teleop") or why neutral ("estop", "timeout", "malformed", "no command")."""
    deadline: float
    """Monotonic time at which this decision expires (the watchdog's next wake-up)."""


class CommandMux:
    """Priority mux with watchdog and e-stop latch. Thread-safe: callbacks offer, the loop decides.

    :param controller: the only source accepted on the cmd channel.
    :param teleop_source: the only source accepted on the teleop channel.
    """

    def __init__(self, controller: str, teleop_source: str, timeout_s: float, teleop_hold_s: float):
        self.controller, self.teleop_source = controller, teleop_source
        self.timeout_s, self.teleop_hold_s = timeout_s, teleop_hold_s
        self._lock = threading.Lock()
        self._ctrl: tuple[DriveCommand, float] | None = None
        self._tele: tuple[DriveCommand, float] | None = None
        self._last_tele = -math.inf
        self._malformed_at = -math.inf
        self.estopped = False
        self.refused = 0
        self.malformed = 0
        self.accepted = 0

    def offer(self, cmd: DriveCommand, channel: str, now: float) -> bool:
        """A valid DriveCommand arrived on ``channel`` ("cmd" or "teleop") at monotonic ``now``."""
        want = self.controller if channel == "cmd" else self.teleop_source
        with self._lock:
            if cmd.source != want:
                self.refused += 1
                return False
            self.accepted += 1
            if channel == "teleop":
                self._tele = (cmd, now)
                self._last_tele = now
            else:
                self._ctrl = (cmd, now)
            return True

    def reject(self, channel: str, now: float) -> None:
        """A malformed payload arrived on ``channel``: whatever that channel said no longer holds."""
        with self._lock:
            self.malformed += 1
            self._malformed_at = now
            if channel == "teleop":
                self._tele = None
            else:
                self._ctrl = None

    def estop(self, payload: bytes) -> None:
        """Any payload latches the e-stop; exactly b"clear" clears it."""
        with self._lock:
            self.estopped = payload.strip().lower() != b"clear"

    def decide(self, now: float) -> Decision:
        far = now + 3600.0
        with self._lock:
            if self.estopped:
                return Decision(None, "estop", far)
            if self._tele is not None and now - self._tele[1] < self.timeout_s:
                return Decision(self._tele[0], "teleop", self._tele[1] + self.timeout_s)
            hold_until = self._last_tele + self.teleop_hold_s
            if now < hold_until:
                return Decision(None, "teleop hold", hold_until)
            if self._ctrl is not None and now - self._ctrl[1] < self.timeout_s:
                return Decision(self._ctrl[0], "controller", self._ctrl[1] + self.timeout_s)
            if self._ctrl is not None or self._tele is not None:
                return Decision(None, "timeout", far)
            if now - self._malformed_at < self.timeout_s:
                return Decision(None, "malformed", far)
            return Decision(None, "no command", far)
