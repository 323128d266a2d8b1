"""What the actuator sends, decided without I/O: calibration mapping, priority mux, watchdog, e-stop.

Mapping (f1tenth convention, XTENTH calibration by default):
- throttle T in [0, 1] -> speed v (m/s): ``throttle_map = "sim"`` uses the simulator's
  steady-state speed for T, i.e. the wheel speed w solving ``c_quad w^2 + c_lin w = gain T``
  (the car file's friction model at rest) times wheel_radius and agent_speed_scale: what T meant
  to the policy while it learnt (full throttle = 2.7 m/s with the slash defaults). ``"linear"``
  is ``v = T * speed_max_mps``. Then ERPM = speed_to_erpm_gain * v + offset, clipped to erpm_max
  (speed_mode "rpm"); or duty = T * duty_max; or current = T * current_max_a.
- steering angle delta (rad, + left) -> servo = gain * delta + offset, clipped to the servo limits.

The mux (ackermann_mux style, one explicit order; :data:`PRIORITY`), highest first:

1. e-stop latch (key ``estop``): any payload latches, exactly ``clear`` clears; neutral.
2. safety brake (key ``safety``, source ``safety``): the supervisor's brake request (motor
   brake, its steering angle, normally centred); services/safety publishes one per scan while
   it brakes and stops publishing to release, so the brake ends ``safety_timeout_s`` later.
3. teleop (key ``teleop``, source ``teleop``): overrides, and holds the inputs below it off for
   ``teleop_hold_s`` after its last command.
4. ROS drive (key ``drive_ros``, source ``ros``): /drive from ROS 2.
5. controller (key ``cmd``, source = the configured controller: policy, baseline, ...).
Otherwise neutral (brake/zero/coast per config) with the steering centred.

Each input is fresh while younger than its own timeout since it arrived (:class:`MuxInput`); a
malformed payload on an input discards that input's command at once; a command from another
source than the input's is refused and counted. The simulator runs this same class (sim time
in lockstep), so the sim and the car arbitrate identically.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

from racecav.common import keys
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

    def brake_frames(self, steering_angle: float = 0.0) -> list[bytes]:
        """The safety supervisor's brake: motor brake current (whatever ``neutral`` says: a
        requested brake must brake) and the steering angle given."""
        return [vp.set_current_brake(self.cfg.brake_current_a), vp.set_servo_pos(self.servo(steering_angle))]

    def decision_frames(self, d: "Decision") -> list[bytes]:
        """Frames for a mux decision: drive, safety brake, or neutral."""
        if d.cmd is None:
            return self.neutral_frames()
        if d.brake:  # the safety supervisor's brake, or a controller's braking command
            return self.brake_frames(d.cmd.steering_angle)
        return self.drive_frames(d.cmd)

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
    """Who drives ("safety", "teleop", "ros", "controller") or why neutral ("estop", "teleop
    hold", "timeout", "malformed", "no command")."""
    deadline: float
    """Time at which this decision expires (the watchdog's next wake-up)."""
    since: float = -math.inf
    """Arrival time of the winning command (-inf for neutral)."""

    @property
    def brake(self) -> bool:
        """True when the motor must brake: neutral, the safety supervisor's brake, or a command
        that brakes (DriveCommand.brake: a policy trained with a brake action)."""
        return self.cmd is None or self.reason == "safety" or self.cmd.brake


@dataclass(frozen=True)
class MuxInput:
    """One input of the mux.

    :param channel: its key leaf (keys.SAFETY, keys.TELEOP, ...), also the name offers use.
    :param source: the only DriveCommand.source accepted; None = any (the simulator's cmd).
    :param timeout_s: a command is in force this long after it arrived.
    :param reason: the Decision.reason while it drives.
    """

    channel: str
    source: str | None
    timeout_s: float
    reason: str


PRIORITY = (keys.SAFETY, keys.TELEOP, keys.DRIVE_ROS, keys.CMD)
"""Inputs below the e-stop latch, highest priority first."""

HELD_BY_TELEOP = (keys.DRIVE_ROS, keys.CMD)
"""Inputs muted for teleop_hold_s after a teleop command."""


class CommandMux:
    """Priority mux with per-input timeouts and the e-stop latch (order: module docstring).

    Thread-safe: callbacks offer, the loop decides. Times are seconds of one clock of the
    caller's choice (monotonic on the car, sim time in lockstep).

    :param controller: the only source accepted on the cmd input (None: any).
    :param teleop_source: the only source accepted on the teleop input.
    :param timeout_s: timeout of the cmd input (and of teleop unless teleop_timeout_s is given).
    :param teleop_hold_s: after a teleop command, ROS drive and controller are muted this long.
    :param safety_source, safety_timeout_s: the safety brake input.
    :param ros_source, ros_timeout_s: the ROS /drive input.
    """

    def __init__(self, controller: str | None, teleop_source: str, timeout_s: float, teleop_hold_s: float,
                 safety_source: str = "safety", safety_timeout_s: float = 0.2, ros_source: str = "ros",
                 ros_timeout_s: float = 0.25, teleop_timeout_s: float | None = None):
        self.controller, self.teleop_source = controller, teleop_source
        self.timeout_s, self.teleop_hold_s = timeout_s, teleop_hold_s
        self.inputs = {i.channel: i for i in (
            MuxInput(keys.SAFETY, safety_source, safety_timeout_s, "safety"),
            MuxInput(keys.TELEOP, teleop_source, timeout_s if teleop_timeout_s is None else teleop_timeout_s,
                     "teleop"),
            MuxInput(keys.DRIVE_ROS, ros_source, ros_timeout_s, "ros"),
            MuxInput(keys.CMD, controller, timeout_s, "controller"))}
        self._lock = threading.Lock()
        self._latest: dict[str, tuple[DriveCommand, float]] = {}
        self._last_tele = -math.inf
        self._malformed_at = -math.inf
        self.estopped = False
        self.refused = 0
        self.malformed = 0
        self.accepted = 0
        self.accepted_by = {i.reason: 0 for i in self.inputs.values()}
        """Commands accepted per input (by reason name), for the status."""

    @classmethod
    def from_config(cls, acfg: ActuatorConfig, controller: str | None = "", timeout_s: float | None = None
                    ) -> "CommandMux":
        """The mux the actuator section describes; the simulator passes ``controller=None``
        (it accepts any controller) and its own watchdog as the cmd ``timeout_s``."""
        return cls(acfg.controller if controller == "" else controller, acfg.teleop_source,
                   acfg.timeout_s if timeout_s is None else timeout_s, acfg.teleop_hold_s,
                   safety_source=acfg.safety_source, safety_timeout_s=acfg.safety_timeout_s,
                   ros_source=acfg.ros_source, ros_timeout_s=acfg.ros_timeout_s,
                   teleop_timeout_s=acfg.timeout_s)

    def offer(self, cmd: DriveCommand, channel: str, now: float) -> bool:
        """A valid DriveCommand arrived on ``channel`` (a key leaf: cmd, teleop, safety,
        drive_ros) at time ``now``; False (counted) if the source is not that input's."""
        inp = self.inputs[channel]
        with self._lock:
            if inp.source is not None and cmd.source != inp.source:
                self.refused += 1
                return False
            self.accepted += 1
            self.accepted_by[inp.reason] += 1
            self._latest[channel] = (cmd, now)
            if channel == keys.TELEOP:
                self._last_tele = now
            return True

    def reject(self, channel: str, now: float) -> None:
        """A malformed payload arrived on ``channel``: whatever that input said no longer holds."""
        with self._lock:
            self.malformed += 1
            self._malformed_at = now
            self._latest.pop(channel, None)

    def estop(self, payload: bytes) -> None:
        """Any payload latches the e-stop; exactly b"clear" clears it (not "CLEAR", not
        " clear\n": a mistyped clear must leave the car stopped)."""
        with self._lock:
            self.estopped = bytes(payload) != b"clear"

    def lost(self, channel: str) -> None:
        """The producer of ``channel`` died (its liveliness token vanished): what it said no
        longer holds, at once rather than after the input's timeout (not counted as malformed)."""
        with self._lock:
            self._latest.pop(channel, None)

    def forget(self) -> None:
        """Drop every input's command (not the e-stop latch): the simulator's new episode starts
        with no command in force, whatever the last one said."""
        with self._lock:
            self._latest.clear()
            self._last_tele = -math.inf
            self._malformed_at = -math.inf

    def decide(self, now: float) -> Decision:
        far = now + 3600.0
        with self._lock:
            if self.estopped:
                return Decision(None, "estop", far)
            hold_until = self._last_tele + self.teleop_hold_s
            for channel in PRIORITY:
                if channel in HELD_BY_TELEOP and now < hold_until:
                    return Decision(None, "teleop hold", hold_until)
                got = self._latest.get(channel)
                inp = self.inputs[channel]
                if got is not None and now - got[1] < inp.timeout_s:
                    return Decision(got[0], inp.reason, got[1] + inp.timeout_s, got[1])
            if self._latest:
                return Decision(None, "timeout", far)
            if now - self._malformed_at < self.timeout_s:
                return Decision(None, "malformed", far)
            return Decision(None, "no command", far)
