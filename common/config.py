"""Typed configuration: every default of the project lives here.

Sources, later wins: the defaults below, a TOML file (``--config``), then environment variables
``RACECAV_<SECTION>__<FIELD>`` (e.g. ``RACECAV_BUS__CAR=car1``; values are parsed as JSON when they
can be, so ``RACECAV_BUS__CONNECT='["tcp/10.0.0.2:7447"]'`` works). An invalid file or value
raises :class:`ConfigError` naming the field; the CLI turns it into exit code 2.

Each service owns one section. Physical car, world and lidar parameters are not configuration
of a run: they are data files read through :mod:`racecav.common.world`.
"""

from __future__ import annotations

import hashlib
import json
import os
import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator


class Section(BaseModel):
    """Base of every section: unknown keys are errors (a typo must not be silently ignored)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class BusConfig(Section):
    """How a process joins the car's Zenoh network."""

    car: str = Field("car0", pattern=r"^[A-Za-z0-9_-]+$")
    """Car name: the second level of every key (racecav/<car>/...)."""
    connect: list[str] = ["tcp/127.0.0.1:7447"]
    """Router endpoints a service connects to (explicit: multicast scouting is off)."""
    mode: Literal["client", "peer"] = "client"
    """client: every message goes through the car's router. peer: services still meet at the
    router, then connect to each other and exchange data directly (one hop less: see
    docs/benchmarks.md, bus)."""
    listen: list[str] = ["tcp/127.0.0.1:0"]
    """Peer mode: where this process accepts its peers' links (port 0: any free port; the router
    tells the others). Ignored in client mode."""
    multicast_scouting: bool = False
    """Off by default: unreliable in containers and CI, and a security hole on the car."""
    user: str | None = None
    """Zenoh user/password login (the deployed router requires it)."""
    password: str | None = None
    tls_root_ca: Path | None = None
    """CA certificate that signed the router's certificate (tls/ endpoints)."""
    tls_cert: Path | None = None
    """Client certificate and key for mutual TLS."""
    tls_key: Path | None = None
    zenoh_config: Path | None = None
    """A full zenoh JSON5 config file to start from; the fields above are applied on top."""
    status_log_period_s: float = Field(5.0, gt=0)
    """Minimum period between two log lines about invalid input (rate limit)."""
    max_payload_bytes: int = Field(65536, gt=0)
    """Payloads larger than this are rejected before decoding."""
    reconnect_initial_s: float = Field(0.1, gt=0, le=10)
    """A client that lost its router retries after this long, then each time 1.5x longer ..."""
    reconnect_max_s: float = Field(0.25, gt=0, le=60)
    """... up to this period (zenoh's defaults, 1 s to 4 s, meant 2.5 s without commands after a
    router restart). A retry is one TCP connect on loopback: cheap."""


class RouterConfig(Section):
    """The car's router (``racecav router``)."""

    listen: list[str] = ["tcp/127.0.0.1:7447"]
    """Endpoints the router listens on. Add e.g. tls/0.0.0.0:7448 to reach it from the network."""
    config_file: Path | None = None
    """A zenoh JSON5 router config (access control, auth, TLS): see deploy/."""


class SensorConfig(Section):
    """The real lidar (``racecav sensor``): RPLIDAR S2 driver and scan preprocessing."""

    port: str = "/dev/rplidar"
    """Serial device; /dev/rplidar is the udev symlink in deploy/ (CP210x 10c4:ea60)."""
    baudrate: int = Field(1_000_000, gt=0)
    """The S2 talks at 1,000,000 baud (A-series: 115200 or 256000)."""
    scan_mode: int | None = Field(None, ge=0)
    """Scan mode id; None = the device's typical mode (DenseBoost on the S2)."""
    motor_rpm: int = Field(600, ge=0, le=65535)
    """Motor speed via A8 (600 rpm = 10 revolutions/s, the scan rate); 0 = leave it alone."""
    car: str = "slash"
    """Car file (common/data/cars) whose lidar_mount.yaw says where the device's 0 deg points."""
    mount_yaw_rad: float | None = None
    """Override of the car file's lidar_mount.yaw (rad, CCW from the car's heading)."""
    scan: Literal["paper", "wide"] = "wide"
    """The scan published: wide = common/lidar.WIDE_SCAN (338 rays over +-89.7 deg at the paper's
    spacing), which holds every view: the shipped avoid policy's (wide) and the paper's, so every
    controller takes its own view out of it (services/controller.py); paper = the car's 170 rays
    over 90 deg only (enough for the paper's policies and MPC-APF, 2x fewer bytes)."""
    reset_wait_s: float = Field(0.002, ge=0)
    """Pause after RESET before the first request: 2 ms, what Slamtec's "RPLIDAR Interface
    Protocol and Application Notes" documents (section "Core Reset (RESET) Request", Fig. 4-3:
    "host systems should wait for at least 2 milliseconds (ms) before sending another
    request"). The core then boots (an S2: about 2 s); the driver polls GET_INFO meanwhile."""
    reset_poll_s: float = Field(0.05, gt=0)
    """Period of GET_INFO after RESET until the rebooted device answers (requests sent while it
    boots are dropped)."""
    reset_timeout_s: float = Field(2.0, gt=0)
    """A device that has not answered GET_INFO this long after RESET is reset again."""
    silence_timeout_s: float = Field(0.3, gt=0)
    """No bytes at all for this long while scanning (a stopped device: health error, protection
    stop) => ask the health, reset. A scanning S2 sends ~67 kB/s without pause."""
    spinup_s: float = Field(0.5, ge=0)
    """Pause between motor start and SCAN (some S2 firmware refuses an early SCAN)."""
    data_timeout_s: float = Field(1.0, gt=0)
    """No scan data for this long => reset and restart the scan."""
    reconnect_s: float = Field(0.1, gt=0)
    """Retry period for reopening a vanished port (USB unplugged): one open() of a missing path
    is cheap, and this bounds the replug -> first scan time (<= 1 s: docs/reliability.md)."""
    def driver_timings(self) -> dict[str, float]:
        """The timing keyword arguments of :class:`~racecav.services.sensor.rplidar_driver.RplidarDriver`."""
        return {k: getattr(self, k) for k in ("reset_wait_s", "reset_poll_s", "reset_timeout_s", "spinup_s",
                                              "data_timeout_s", "silence_timeout_s", "reconnect_s")}

    max_gap_deg: float = Field(6.0, ge=0)
    """Widest hole between good samples that preprocessing fills by interpolation (deg)."""
    spike_abs_m: float = Field(0.3, ge=0)
    """An isolated spike differs from both neighbours by more than this (m) ..."""
    spike_rel: float = Field(0.15, ge=0)
    """... and by more than this fraction of their range."""
    downsample: Literal["interp", "nearest", "min"] = "interp"
    """How the 170 rays are taken from ~800 frontal samples: interp (like the simulator's single
    ray per angle), nearest, or min over each ray's bin (conservative)."""


class ActuatorConfig(Section):
    """The VESC (``racecav actuator``): command mapping, calibration, safety.

    Calibration defaults are XTENTH-CAR's (the paper's car): ERPM = speed_to_erpm_gain * v +
    speed_to_erpm_offset; servo = steering_angle_to_servo_gain * delta + steering_angle_to_servo_offset,
    clipped to [servo_min, servo_max].
    """

    port: str = "/dev/vesc"
    """Serial device of the VESC (USB CDC 0483:5740; the baud rate is ignored by CDC)."""
    baudrate: int = Field(115200, gt=0)
    controller: str = Field("policy", min_length=1)
    """The only source accepted on the cmd key (policy, baseline, ...); others are refused."""
    teleop_source: str = Field("teleop", min_length=1)
    """Source accepted on the teleop key; it overrides the controller while fresh."""
    timeout_s: float = Field(0.25, gt=0)
    """Watchdog: no fresh command for this long => motor neutral/brake and steering centred.
    2.5 control periods: commands come at the S2's ~10 Hz scan rate, so a 100 ms timeout would
    brake between two on-time commands whenever one is a little late (measured: 5 brake
    episodes in 2 s of driving). Set 0.1 for a controller running faster than 10 Hz."""
    teleop_hold_s: float = Field(0.5, ge=0)
    """After a teleop command, controller commands are ignored for this long (priority mux)."""
    safety_source: str = Field("safety", min_length=1)
    """Source accepted on the safety key: the supervisor's brake, above teleop (services/safety)."""
    safety_timeout_s: float = Field(0.2, gt=0)
    """A safety brake holds this long after the supervisor's last brake message (it publishes one
    per scan while braking, ~10 Hz): releasing is stopping to publish."""
    ros_source: str = Field("ros", min_length=1)
    """Source accepted on the drive_ros key (ROS 2 /drive), between teleop and the controller."""
    ros_timeout_s: float = Field(0.25, gt=0)
    """Timeout of the ROS drive input (ackermann_mux uses 0.2 s)."""
    state_dir: Path | None = None
    """Where the e-stop latch is kept across restarts (file ``estop-<car>.json``). None: systemd's
    $STATE_DIRECTORY (the unit's StateDirectory=racecav, /var/lib/racecav) or
    ~/.local/state/racecav. Design: docs/reliability.md."""
    sim_scans_drive: bool = False
    """Obey commands that answer simulator scans (DriveCommand.scan_source "sim"): only for
    hardware in the loop with the car on a stand. Off: they are refused and counted
    (``sim_refused``), so a simulator started by mistake, or from a desktop, cannot drive the car."""
    follow_liveliness: bool = True
    """Brake the moment the controller's liveliness token (racecav/<car>/<controller>/alive)
    vanishes (a dead process: ~ms), instead of waiting for timeout_s (the backstop for a live
    but silent controller)."""
    rate_hz: float = Field(50.0, gt=0)
    """Period at which the current command (or neutral) is re-sent; the VESC drops a motor
    that hears nothing for its app timeout."""
    values_hz: float = Field(10.0, ge=0)
    """GET_VALUES polling rate for the status (0 = never)."""
    car: str = "slash"
    """Car file whose throttle model defines speed(T) for throttle_map = "sim"."""
    speed_mode: Literal["rpm", "duty", "current"] = "rpm"
    """How throttle reaches the motor: SET_RPM (speed control, the f1tenth way), SET_DUTY, SET_CURRENT."""
    throttle_map: Literal["sim", "linear"] = "sim"
    """Throttle T -> speed: "sim" = the simulator's steady-state speed for T (the car file's
    friction model times agent_speed_scale: what the policy learnt T means); "linear" = T * speed_max_mps."""
    speed_max_mps: float = Field(5.04, gt=0)
    """Speed at T = 1 for throttle_map = "linear" (23250 ERPM / 4614 = XTENTH's limit)."""
    speed_to_erpm_gain: float = 4614.0
    speed_to_erpm_offset: float = 0.0
    erpm_max: float = Field(23250.0, gt=0)
    """ERPM clip (XTENTH speed_max)."""
    duty_max: float = Field(0.2, gt=0, le=0.95)
    """Duty at T = 1 for speed_mode = "duty"."""
    current_max_a: float = Field(20.0, gt=0)
    """Motor current at T = 1 for speed_mode = "current"."""
    steering_angle_to_servo_gain: float = -1.2135
    steering_angle_to_servo_offset: float = Field(0.5304, ge=0, le=1)
    """Servo position of a centred wheel (steering angle 0)."""
    servo_min: float = Field(0.15, ge=0, le=1)
    servo_max: float = Field(0.85, ge=0, le=1)
    neutral: Literal["brake", "rpm0", "coast"] = "brake"
    """What "stop" sends: SET_CURRENT_BRAKE(brake_current_a), SET_RPM 0, or SET_CURRENT 0."""
    brake_current_a: float = Field(20.0, ge=0)

    @model_validator(mode="after")
    def _check_servo(self) -> "ActuatorConfig":
        if self.servo_min > self.servo_max:
            raise ValueError("servo_min: must not exceed servo_max")
        return self


class PerturbConfig(Section):
    """Sim-to-real perturbations (common/perturb.py; presets with their sources in
    common/data/perturbations.toml and docs/robustness.md). Every default is the ideal world.
    On the command line and in ``RACECAV_SIM__PERTURB``: a preset name, ``key=value`` pairs, or
    both (``s2-nominal,latency_s=0.05``)."""

    range_noise_m: float = Field(0.0, ge=0, le=1)
    """Gaussian range noise: standard deviation (m) independent of the range ..."""
    range_noise_rel: float = Field(0.0, ge=0, le=0.5)
    """... and proportional to it (fraction); the two add in quadrature."""
    dropout: float = Field(0.0, ge=0, le=0.9)
    """Share of rays that return nothing (the S2 reports distance 0; the sensor service then fills
    holes up to SensorConfig.max_gap_deg, and so does the sim: services/sensor/preprocess.py)."""
    mount_yaw_rad: float = Field(0.0, ge=-0.5, le=0.5)
    """The lidar is mounted turned by this (rad, CCW) while every consumer assumes the car file's."""
    scan_jitter_s: float = Field(0.0, ge=0, lt=0.1)
    """Each scan reaches the controller up to this much later (s, uniform; lockstep only)."""
    latency_s: float = Field(0.0, ge=0, lt=1)
    """Extra latency between the scan and the command (s): a slower computer (lockstep only)."""
    actuator_delay_s: float = Field(0.0, ge=0, lt=1)
    """Delay between the command and the actuators acting on it (s; lockstep only)."""
    steer_offset_rad: float = Field(0.0, ge=-0.1, le=0.1)
    """Steering trim error: the wheels point this far (rad, CCW) from the commanded angle."""
    motor_gain: float = Field(1.0, gt=0, le=2)
    """The wheel speed reached for a throttle is this times what the controller meant."""
    friction: float = Field(1.0, gt=0, le=2)
    """Tyre-floor friction coefficient (1.0: the car file's tyre on a lab floor)."""
    mass_scale: float = Field(1.0, gt=0, le=3)
    """The car's mass (and yaw inertia) times this."""

    @model_validator(mode="before")
    @classmethod
    def _from_text(cls, v):
        if isinstance(v, str):  # a preset name and/or key=value pairs (common/perturb.py)
            return parse_text(v)
        return v

    def active(self) -> dict[str, float]:
        """The fields that differ from the ideal world."""
        return {k: v for k, v in self.model_dump().items() if v != type(self).model_fields[k].default}

    def timing(self) -> bool:
        """Perturbs the time a command takes effect (needs a lockstep sim)."""
        return bool(self.scan_jitter_s or self.latency_s or self.actuator_delay_s)

    def text(self) -> str:
        """Canonical short text: "nominal", or the active fields as sorted key=value pairs."""
        act = self.active()
        return ",".join(f"{k}={v:g}" for k, v in sorted(act.items())) if act else "nominal"



PERTURB_PRESETS_FILE = Path(__file__).parent / "data" / "perturbations.toml"
"""Named perturbations with the source of every number (docs/robustness.md). The parsing lives
here, beside PerturbConfig, which accepts its text; the model itself is common/perturb.py."""


def perturb_keys() -> list[str]:
    """The fields a perturbation preset or ``--perturb`` may set."""
    return list(PerturbConfig.model_fields)


def _check_keys(data: dict, where: str) -> None:
    for k in data:
        if k not in PerturbConfig.model_fields:
            raise ValueError(f"{where}: unknown key {k!r} (known: {', '.join(perturb_keys())})")


def load_presets(path: Path | str | None = None) -> dict[str, dict]:
    """Preset name -> its non-default fields, validated; ValueError naming file, preset and key."""
    path = Path(path or PERTURB_PRESETS_FILE)
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"perturbation presets {path}: {e}") from None
    out = {}
    for name, table in data.items():
        if not isinstance(table, dict):
            raise ValueError(f"perturbation presets {path}: {name!r} is not a [preset] table")
        _check_keys(table, f"perturbation presets {path} [{name}]")
        try:
            PerturbConfig.model_validate(table)
        except Exception as e:  # a value out of its range: one line
            raise ValueError(f"perturbation presets {path} [{name}]: {str(e).splitlines()[-2].strip()}") from None
        out[name] = dict(table)
    return out


def parse_text(text: str, presets: dict[str, dict] | None = None) -> dict:
    """``"PRESET"``, ``"key=value,..."`` or both (later items win) -> PerturbConfig fields.

    :raises ValueError: one line naming the unknown preset or key, or the bad value.
    """
    presets = load_presets() if presets is None else presets
    out: dict = {}
    for item in filter(None, (x.strip() for x in text.split(","))):
        key, eq, value = item.partition("=")
        key = key.strip()
        if not eq:
            if key == "nominal":
                continue
            if key not in presets:
                raise ValueError(f"perturb: unknown preset {key!r} (known: nominal, {', '.join(presets)}; "
                                 f"or key=value with keys {', '.join(perturb_keys())})")
            out.update(presets[key])
            continue
        _check_keys({key: 0}, "perturb")
        try:
            out[key] = float(value)
        except ValueError:
            raise ValueError(f"perturb: {key}={value.strip()!r} is not a number") from None
    return out


class SimConfig(Section):
    """The simulator service (``racecav sim``): PyBullet world playing the car (HIL stand-in)."""

    scenario: str = "head-to-head"
    """Scenario name (common/data/scenarios) or TOML path; "racetrack" for the training world."""
    mode: Literal["realtime", "lockstep"] = "realtime"
    """realtime: the world runs against the wall clock, a command applies when it arrives;
    lockstep: each control step waits for the command answering the latest scan and applies it
    after the controller's reported compute latency (deterministic)."""
    real_time_factor: float = Field(1.0, ge=0)
    """Sim seconds per wall second in realtime mode; 0 = as fast as possible."""
    watchdog_s: float = Field(0.25, gt=0)
    """Realtime: the last command is held at most this long (wall), then the car brakes. 2.5 scan
    periods: one late scan must not brake the car, a dead controller must."""
    lockstep_timeout_s: float = Field(2.0, gt=0)
    """Lockstep: republish the scan if no answer came within this (wall) time; keep waiting."""
    lockstep_compute_ms: float | None = Field(None, ge=0, lt=1000)
    """Lockstep: charge every answer this compute time instead of the ``compute_ns`` it reports
    (None: the reported one). A measured compute time jitters by microseconds from run to run, so
    a controller that measures its own (MPC-APF, the policy service) never repeats a lockstep run
    to the bit; with a fixed charge it does, at the cost of the latency the mode exists to charge
    (``RACECAV_SIM__LOCKSTEP_COMPUTE_MS=10 racecav eval ...``; the runs' sim_counters record it)."""
    wait_for_controller: bool = True
    """Realtime: an episode's clock starts when the first command after its reset arrives (its
    first scan is republished every 0.5 s until then), so a trial never starts uncontrolled."""
    seed: int = Field(0, ge=0, le=2**32 - 1)
    """Seed of the first episode; episode k uses seed + k unless a reset names one."""
    on_end: Literal["hold", "reset"] = "hold"
    """At contact or the end of the trial: hold (stop stepping, report done) or start the next
    episode."""
    lidar_all: bool = False
    """Cast the lidar for every car (only needed by a traffic driver that observes)."""
    heading: Literal["default", "reversed"] | None = None
    """Override the racetrack scenario's agent heading."""
    car: str = "slash"
    """Car file (common/data/cars)."""
    lidar_range_max: float | None = Field(None, gt=0)
    """Override the car file's lidar range (m); None = the car's (12 m)."""
    scan: Literal["paper", "wide"] = "wide"
    """The scan published: wide = common/lidar.WIDE_SCAN (338 rays over +-89.7 deg at the paper's
    spacing), which holds every view: the shipped avoid policy's (wide) and the paper's, so every
    controller takes its own view out of it (services/controller.py); paper = the car's 170 rays
    over 90 deg only (enough for the paper's policies and MPC-APF, 2x fewer bytes)."""
    publish_obstacles: bool = True
    """Publish ground-truth ObstacleStates every step."""
    lockstep_safety: bool = False
    """Lockstep: also wait for the safety supervisor's verdict on each scan before stepping, so
    its brake applies to the scan it answers (set when ``racecav safety`` runs, e.g. ``racecav
    eval --safety on``)."""
    perturb: PerturbConfig = PerturbConfig()
    """Sim-to-real perturbations of the agent's lidar, timing and car (``racecav sim --perturb``);
    the timing ones need mode lockstep (the sim refuses them in realtime)."""


class SafetyConfig(Section):
    """The emergency-brake supervisor (``racecav safety``): per-ray instantaneous time to
    collision from each scan and the ego speed; design in docs/controllers.md."""

    car: str = "slash"
    """Car file: lidar mount and body box (the lidar-to-bumper distance of each ray)."""
    threshold_s: float = Field(0.4, gt=0)
    """Brake when the scan's iTTC (see min_rays) is below this for debounce_scans scans in a row.
    0.4 s at 2.7 m/s is 1.1 m of gap; braking from 2.7 m/s takes ~0.3 s (locked wheels)."""
    debounce_scans: int = Field(2, ge=1)
    """Consecutive scans below the threshold before braking (1 = no debounce)."""
    min_rays: int = Field(2, ge=1)
    """A scan's iTTC is its min_rays-th smallest ray value: one spurious ray does not brake."""
    release_s: float = Field(0.8, gt=0)
    """Hysteresis: release when the scan's iTTC at the speed max(v, release_probe_mps) is above
    this ..."""
    release_scans: int = Field(2, ge=1)
    """... for this many scans in a row ..."""
    release_probe_mps: float = Field(1.0, ge=0)
    """A braked car is released only when it could drive off at this speed: a stopped car stays
    braked in front of a wall or a car still crossing (0: release at standstill)."""
    min_brake_s: float = Field(0.3, ge=0)
    """... and the brake has lasted at least this long (scan time)."""
    min_speed_mps: float = Field(0.1, ge=0)
    """Below this ego speed nothing is braked (a car standing at a wall may drive away)."""
    eps_mps: float = Field(0.01, gt=0)
    """Closing speeds below this count as this (iTTC = gap / max(v cos theta, eps))."""
    path_gate: Literal["none", "straight", "arc"] = "arc"
    """Rays that may brake: all ("none", the plain F1TENTH node), those hitting the straight-ahead
    swept box, or those hitting the band swept at the current steering angle ("arc"). Measured
    false brakes per gate: docs/controllers.md."""
    lateral_margin_m: float = Field(0.1, ge=0)
    """False-brake candidate: a brake whose rays all hit outside the car's straight-ahead swept
    box widened by this (m) on each side (e.g. a wall beside a corridor, a bend)."""
    ego_state: Literal["auto", "state", "model"] = "auto"
    """Ego speed source, as the baseline's: the state key while fresh, else the commanded
    throttle through the car model (services/baseline/ego.py)."""
    max_state_age_s: float = Field(0.3, gt=0)
    """A VehicleState older than this (wall clock) is not used."""
    initial_speed: float = Field(1.0, ge=0)
    """Model speed (m/s) before any state or command is known."""
    max_scan_age_s: float = Field(0.25, gt=0)
    """A real scan whose stamp is older than this is not judged (counted stale)."""
    reset_jump_m: float = Field(1.0, gt=0)
    """Two consecutive states this far apart mean the car was moved (a simulator reset, a
    relocalisation): the brake logic starts over instead of carrying a brake into the new place."""
    steer_timeout_s: float = Field(0.25, gt=0)
    """The brake command keeps the controller's steering angle if its last command is younger
    than this, else it centres the wheels."""


class EnvConfig(Section):
    """The training env ``racecav/Overtake-v0`` and its batched VecEnv (training/env.py)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, use_attribute_docstrings=True)

    backend: Literal["fast", "bullet"] = "fast"
    """fast: the numba batched world (training); bullet: the PyBullet reference world."""
    world: str = "racetrack"
    car: str = "slash"
    heading: Literal["default", "reversed"] = "default"
    """Agent with the traffic (default) or against it (reversed)."""
    n_obstacles: int = Field(15, ge=0, le=15)
    """Obstacle cars per world; 0 for the racing stage."""
    driver: str = "centerline"
    """Traffic driver: "centerline" (pure pursuit) or "policy:PATH" (a racing policy file)."""
    control_period_s: float | None = Field(None, gt=0)
    """None: the car's control_period_s (0.1 s, the RPLIDAR S2 scan period)."""
    time_limit_s: float = Field(60.0, gt=0)
    """Episode time limit: truncation, not termination (about two laps at the agent's top speed)."""
    agent_speed_scale: float | None = Field(None, gt=0)
    """None: the car's agent_speed_scale with obstacles, 1.0 without (the racing stage trains at
    the speed of the cars its policy will drive)."""
    n_envs: int = Field(64, ge=1)
    """Worlds stepped together by the fast VecEnv."""
    parallel: bool = False
    """Fast backend: lidar on numba's threads (faster with a free core; contention when several
    runs share the 2 cores)."""
    scenarios: str | None = None
    """Scenario episodes: a suite (NAME or folder with suite.json: its train split), a folder of
    scenario files, or one file. None: traffic episodes only."""
    scenario_share: float = Field(0.0, ge=0, le=1)
    """Share of the batch's worlds that run scenario episodes (the rest: traffic episodes)."""
    scenario_maps: int = Field(0, ge=0)
    """Scenario episodes on at most this many maps (world geometries) at once, drawn from the
    scenarios' maps and drawn again by ``FastVecEnv.resample_maps()`` (training/map_pool.py): a
    generated suite has hundreds of maps, one fast world each. 0: every map at once."""
    curriculum: bool = False
    """Scenario episodes: draw files by family, each family weighted by its failure rate over
    its last 200 training episodes (at least 0.1), so training goes where the policy fails;
    False: every train file equally often. Families: each suite's own (its manifest), a
    plain scenario file is its own family (common/scenario.scenario_sources). The training VecEnv's option (training/vec_env.FamilyCurriculum); the single
    gym env draws uniformly."""
    curriculum_boost: dict[str, float] = {}
    """With curriculum: family -> factor on its draw weight (e.g. ``paper-timed/cross-left=3``;
    on the CLI "FAMILY=W[,FAMILY=W]"), for families that look alike until late (a crossing car to
    pass ahead of vs one to go behind) where failure rates alone weigh them alike. A factor 3 on
    the paper-timed crossings from the left did not move the avoid policy's trade-off (row 21 of
    docs/training.md). {}: the failure rates alone."""

    @field_validator("curriculum_boost", mode="before")
    @classmethod
    def _parse_boost(cls, v):
        if isinstance(v, str):  # the CLI's "FAMILY=W,FAMILY=W"
            out = {}
            for part in filter(None, (x.strip() for x in v.split(","))):
                name, eq, w = part.partition("=")
                try:
                    out[name.strip()] = float(w)
                except ValueError:
                    raise ValueError(f"curriculum_boost: {part!r} is not FAMILY=FACTOR") from None
                if not eq or not name.strip():
                    raise ValueError(f"curriculum_boost: {part!r} is not FAMILY=FACTOR")
            v = out
        if isinstance(v, dict) and any(not isinstance(w, (int, float)) or not w > 0 for w in v.values()):
            raise ValueError(f"curriculum_boost: factors must be > 0 (got {v})")
        return v

    @model_validator(mode="after")
    def _boost_needs_curriculum(self):
        if self.curriculum_boost and not self.curriculum:
            raise ValueError("curriculum_boost: weighs the curriculum's draw; set curriculum too")
        return self

    lidar: Literal["paper", "wide"] = "paper"
    """The scan the policy sees (common/lidar.VIEWS): paper = 170 rays over the frontal 90 deg;
    wide = 169 rays over +-89.7 deg (every second ray of the paper's spacing). The policy's
    metadata carries it; the sim and the sensor then publish common/lidar.WIDE_SCAN."""
    obs_stack: int = Field(1, ge=1, le=4)
    """Observation = the newest ``obs_stack`` scans, newest first (1: the paper's single scan).
    More than one shows motion; the policy service stacks the same way (policy metadata)."""
    obs_stride: int = Field(1, ge=1, le=10)
    """The stacked scans are this many control periods apart (1: consecutive scans). A longer
    baseline shows slow bearing changes: a crossing car that will pass drifts by less than one
    wide ray between consecutive scans (0.1 s), by a few over 0.4 s."""
    progress_reward: float = Field(0.0, ge=0)
    """Reward per metre of progress (along the centerline in the agent's direction, or along a
    scenario ego's initial heading), added to 5 T^2. 0: the paper's reward. ~18.5 matches 5 T^2
    at full speed (2.7 m/s x 0.1 s); without it, turning away from a conflict and circling
    earns as much as driving on."""
    flow_reward: float = Field(0.0, ge=0)
    """Scenario episodes of the fast VecEnv: reward per metre the ego moves along the direction
    of travel of a near crossing car (negative against it; training/flow_reward.py). 0: off."""
    brake_below: float | None = Field(None, gt=-1, le=0)
    """Brake action: a_T below this brakes (wheel speed target 0; the VESC's brake current on
    the car, DriveCommand.brake). None: the paper's action, where a_T <= 0 only coasts. The
    shipped policy's metadata carries it, so the policy service brakes the same way."""


class TrainConfig(Section):
    """One PPO training run (``racecav train racing|overtake``): the defaults are the paper's
    setting (section 3.3; SB3 defaults for the rest); ``--preset fast`` and explicit flags
    override them; the run folder's config.json records the result (training/train.py)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, use_attribute_docstrings=True)

    stage: Literal["racing", "overtake", "dagger"] = "overtake"
    """racing: stage 1 on the empty track; overtake: stage 2 among obstacle cars (and scenarios);
    dagger: the overtake env, the policy imitating the yield teacher (training/dagger.py)."""
    preset: Literal["paper", "fast"] = "paper"
    """The preset the run started from (TRAIN_PRESETS)."""
    seed: int = Field(0, ge=0)
    """PPO and env seed."""
    n_steps: int = Field(2048, ge=1)
    """Rollout steps per env (PPO n_steps)."""
    batch_size: int = Field(64, ge=1)
    """PPO minibatch size."""
    n_epochs: int = Field(10, ge=1)
    """PPO epochs per update."""
    gamma: float = Field(0.99, gt=0, le=1)
    """Discount factor."""
    learning_rate: float = Field(3e-4, gt=0)
    """Adam learning rate."""
    gae_lambda: float = Field(0.95, ge=0, le=1)
    """GAE lambda."""
    clip_range: float = Field(0.2, gt=0)
    """PPO clip range."""
    ent_coef: float = Field(0.0, ge=0)
    """Entropy bonus coefficient."""
    vf_coef: float = Field(0.5, ge=0)
    """Value loss coefficient."""
    max_grad_norm: float = Field(0.5, gt=0)
    """Gradient clipping norm."""
    normalize: bool = False
    """VecNormalize observations and rewards (the statistics ship with the weights)."""
    checkpoint_every: int = Field(5_000_000, ge=1)
    """Samples between checkpoints."""
    init_from: str | None = None
    """Start the weights (and the normalisation of a .vecnorm.pkl beside it) from this SB3 zip."""
    init_std: float | None = Field(None, gt=0)
    """With init_from: reset the action std to this (a converged policy explores too little)."""
    sde_sample_freq: int | None = Field(None, ge=-1)
    """Generalised state-dependent exploration (SB3's ``use_sde``): the action noise is a random
    linear function of the policy's last hidden layer, drawn anew every this many steps (-1: once
    per rollout), so an exploratory turn lasts. None: SB3's independent noise at every step."""
    hidden: int = Field(64, ge=2)
    """Units in each of the two hidden layers of actor and critic (64: the paper's MlpPolicy). A
    ``init_from`` policy must have the same width."""
    env: EnvConfig = EnvConfig(n_envs=1)
    """The training env (heading, obstacles, traffic driver, world, scenarios, observation...)."""
    # dagger stage only (training/dagger.py)
    expert_share: float = Field(0.0, ge=0, le=1)
    """Share of the episodes the teacher drives (DAgger's beta); the policy drives the rest. Every
    step is labelled with the teacher's action either way."""
    expert: Literal["yield", "predictive"] = "yield"
    """The teacher. yield (training/teacher.YieldTeacher): the ``init_from`` policy's own action,
    relabelled in the ``mirror_families`` scenarios: brake while a car in the ego's scan is in or
    closing on the crossing, follow a car ahead, steer round an oncoming or stopped one.
    predictive (training/predictive_teacher.py): knows no family; predicts every actor and takes
    the first clear manoeuvre (scenario worlds only: ``env.scenario_share`` 1). The other teachers
    of the ablation (a privileged planner, the mirror image, tracking, hold, stop and look) are in
    the history at commit 3a95a65."""
    map_resample_every: int = Field(0, ge=0)
    """dagger: rollouts between draws of the scenario worlds' maps (``env.scenario_maps``;
    FastVecEnv.resample_maps). 0: the maps drawn at the start are kept."""
    mirror_families: str = "cross-left"
    """The scenario families (comma-separated; a family of every suite, cross-left, or of one,
    paper-timed/cross-left) whose steps the teacher relabels."""
    bc_balance: bool = False
    """Each imitation minibatch half the steps where the teacher steers round a car
    (YieldTeacher.steered), half its other labels (rows 92-94 of docs/training.md; row 95, the
    shipped avoid, without)."""
    grad_steps: int = Field(400, ge=1)
    """dagger: gradient steps (minibatches of batch_size) after each rollout."""
    dataset_max: int = Field(1_500_000, ge=1)
    """Labelled samples kept (the newest; saved with each checkpoint as dagger-state.pt and resumed)."""


TRAIN_PRESETS: dict[str, dict] = {
    # The paper's PPO setting (section 3.3): the TrainConfig defaults, one env.
    "paper": {"env": {"n_envs": 1}},
    # Chosen by measurement for 2 shared CPU cores (docs/training.md): 64 envs per rollout, the
    # same rollout length per env-step of experience, minibatch 2048, 10 epochs.
    "fast": {"n_steps": 128, "batch_size": 2048, "normalize": True, "checkpoint_every": 1_000_000,
             "env": {"n_envs": 64}},
}


class PolicyConfig(Section):
    """The DRL policy controller (``racecav policy``)."""

    model: str = "avoid"
    """Shipped policy name (avoid: trained on conflicts, the default; reversed, default: the
    paper's; racing) or path to a policy .npz."""
    max_scan_age_s: float = Field(0.25, gt=0)
    """A scan that arrived longer ago than this (wall clock) gets no command: it is counted as
    stale. Also the limit on scan stamp age when the scan is stamped with this host's monotonic
    clock (source "real"); sim stamps are sim time and only the arrival age applies."""
    car: str = "slash"
    """Car file: steering limits of the physical steering angle in the command."""
    backend: Literal["fused", "numpy", "onnxruntime"] = "fused"
    """Inference: fused (one numba kernel, the default), numpy (the reference NumpyPolicy), or
    onnxruntime (the ONNX export of the same weights; extra ``onnx``)."""
    onnx: str | None = None
    """onnxruntime backend: a model.onnx written by ``racecav train export --onnx``; None = build
    the ONNX graph from the weights in memory at start."""


class PerceptionConfig(Section):
    """The baseline's lidar perception: clustering, tracking, moving/static decision
    (services/baseline/perception.py; defaults suit the 1/10 car and its lidar)."""

    max_range: float = Field(6.0, gt=0)
    """Returns farther than this (m) are ignored."""
    gap_m: float = Field(0.12, gt=0)
    """Constant part of the clustering distance threshold (m)."""
    gap_k: float = Field(3.0, gt=0)
    """Range-proportional part: this many ray spacings at the point's range."""
    max_skip: int = Field(2, ge=0)
    """Rays without return that may lie inside one cluster."""
    max_obstacle_extent: float = Field(0.8, gt=0)
    """Clusters longer than this (m, first to last point / bounding diagonal) are boundary."""
    centre_offset: float = Field(0.1, gt=0)
    """The lidar sees a car's near side: its centre lies this far (m) behind the visible points."""
    boundary_spacing: float = Field(0.15, gt=0)
    """Spacing (m) of the boundary points taken from long clusters."""
    gate_m: float = Field(0.5, gt=0)
    """Association gate (m) around a track's predicted position."""
    alpha: float = Field(0.5, gt=0, le=1)
    """Alpha-beta filter position gain."""
    beta: float = Field(0.1, gt=0, le=1)
    """Alpha-beta filter velocity gain."""
    max_speed: float = Field(4.0, gt=0)
    """Velocity estimates are clipped to this (m/s): association glitches must not fling tracks."""
    confirm_hits: int = Field(3, gt=0)
    moving_speed: float = Field(0.5, gt=0)
    """m/s: a confirmed track at least this fast ..."""
    dynamic_hits: int = Field(2, gt=0)
    """... with at least this many detections standing where the previous scan saw free space
    is a moving obstacle; everything else is static."""
    free_margin: float = Field(0.1, ge=0)
    """m: a point counts as previously free if the previous ray went this much farther."""
    free_fraction: float = Field(0.1, gt=0, le=1)
    """Fraction of a cluster's points previously free for a detection to count as dynamic."""
    max_misses: int = Field(3, gt=0)
    coast_s: float = Field(1.0, gt=0)
    """s: a track that left the field of view is kept (predicted) this long."""
    compact_weight: float = Field(1.0, gt=0)
    """Factor on the boundary potential of compact static objects (a parked car, a corner). 1 =
    like walls; 3 (more room) made the ego stall in front of a parked car and hit it in tests."""
    memory_s: float = Field(1.5, gt=0)
    """s: static points that left the field of view are remembered this long."""


class BaselineConfig(Section):
    """The MPC-APF baseline controller (``racecav baseline``); design in docs/controllers.md."""

    car: str = "slash"
    """Car file: model parameters, actuator limits and lidar mount."""
    max_scan_age_s: float = Field(0.25, gt=0)
    """Scans older than this on arrival (wall clock) get no command and are counted stale."""
    obstacles: Literal["lidar", "oracle"] = "lidar"
    """lidar: detect and track obstacles from the scan (evaluation); oracle: ground-truth
    ObstacleStates from the simulator (diagnosis only)."""
    ego_state: Literal["auto", "state", "model"] = "auto"
    """Where ego pose and speed come from: "state" = the state key (sim or odometry), "model" =
    dead reckoning of the car's own commands through the car model, "auto" = the state key while
    it is fresh, the model otherwise."""
    speed_scale: float | None = Field(None, gt=0)
    """Body speed per (wheel speed x wheel radius) in the speed model; None = the car file's
    agent_speed_scale: the ego is the agent, as in training and on the actuator."""
    initial_speed: float = Field(1.0, ge=0)
    """Ego speed (m/s) the dead-reckoning model starts from (scenarios start at 1 m/s)."""
    max_state_age_s: float = Field(0.3, gt=0)
    """A VehicleState older than this (wall clock) is not used (auto falls back to the model)."""
    horizon: int = Field(10, ge=2, le=50)
    """Prediction steps (paper: 10)."""
    dt: float = Field(0.2, gt=0)
    """Prediction step (s): horizon * dt is the look-ahead."""
    v_ref: float = Field(1.0, ge=0)
    """Target speed (m/s) of the speed-tracking term."""
    w_lane: float = Field(1.0, ge=0)
    """Weight of the lateral offset from the lane reference (1/m^2)."""
    w_heading: float = Field(1.0, ge=0)
    """Weight of the heading error to the lane direction (1/rad^2)."""
    w_speed: float = Field(2.0, ge=0)
    """Weight of the speed error ((s/m)^2)."""
    w_obstacle: float = Field(30.0, ge=0)
    """Peak of one obstacle charge's potential."""
    obstacle_margin: float = Field(0.3, gt=0)
    """Clearance (m) beyond contact at which an obstacle charge's Gaussian has fallen to 5 %."""
    obstacle_charges: int = Field(3, ge=1, le=7)
    """Charges along an obstacle car's length (line charge)."""
    w_boundary: float = Field(5.0, ge=0)
    """Peak of one static boundary point's potential."""
    boundary_margin: float = Field(0.25, gt=0)
    """Clearance (m) beyond contact at which a boundary point's Gaussian has fallen to 5 %."""
    w_throttle: float = Field(0.05, ge=0)
    """Input effort: throttle."""
    w_steer: float = Field(0.5, ge=0)
    """Input effort: steering angle (1/rad^2)."""
    w_dsteer: float = Field(2.0, ge=0)
    """Input rate: steering change per step (1/rad^2)."""
    w_dthrottle: float = Field(0.2, ge=0)
    """Input rate: throttle change per step."""
    max_obstacles: int = Field(4, ge=1, le=16)
    """Tracked obstacles passed to the MPC (nearest first)."""
    max_boundary_points: int = Field(24, ge=0, le=128)
    """Static boundary points passed to the MPC (nearest first)."""
    solver: Literal["sqp", "ipopt"] = "sqp"
    """sqp: casadi sqpmethod + qrqp (fast); ipopt: interior point (slower, reference)."""
    max_iter: int = Field(20, ge=1)
    """Solver iteration limit per solve."""
    compile: bool = True
    """Compile the solver's derivative functions to C (system compiler, in the background at
    start, cached under ~/.cache/racecav/mpc); until then and without a compiler casadi's virtual
    machine runs them (same results, about 4x slower)."""
    multi_start: bool = False
    """Also solve from hard-left and hard-right initial guesses when something is near, keep the
    cheapest (the APF cost is non-convex; a single warm start finds only the nearest way)."""
    multi_start_range: float = Field(2.0, gt=0)
    """m: a moving obstacle, or a boundary point closer than this, triggers the multi-start."""
    perception: PerceptionConfig = PerceptionConfig()
    """[baseline.perception] in TOML, RACECAV_BASELINE__PERCEPTION__<FIELD> in the environment."""


class Ros2Config(Section):
    """The ROS 2 mirror (``racecav ros2``): the car's keys as ROS 2 topics over Zenoh, and ROS
    ``/drive`` as a command input of the mux (docs/ros2.md)."""

    mode: Literal["rmw_zenoh", "humble", "bridge"] = "rmw_zenoh"
    """rmw_zenoh: ROS 2 Jazzy or later with rmw_zenoh (RIHS01 type hashes in keys and tokens);
    humble: rmw_zenoh on Humble (TypeHashNotSupported); bridge: zenoh-bridge-ros2dds (plain topic
    keys, CDR, no attachment, no liveliness tokens)."""
    connect: list[str] = []
    """Zenoh endpoints of the ROS side (e.g. an rmw_zenohd router on tcp/127.0.0.1:7448); empty:
    publish on the car's own bus (ROS nodes then connect to the racecav router)."""
    domain_id: int = Field(0, ge=0, le=232)
    """ROS_DOMAIN_ID: the first level of rmw_zenoh keys and tokens."""
    node: str = Field("racecav", pattern=r"^[A-Za-z][A-Za-z0-9_]*$")
    """ROS node name of the mirror (``ros2 node list``)."""
    namespace: str = ""
    """ROS namespace of the node and of relative topic names ("" = global)."""
    bridge_prefix: str = ""
    """bridge mode: the bridge's namespace, prefixed to every key ("" = none)."""
    scan_topic: str = "/scan"
    """sensor_msgs/msg/LaserScan mirror of racecav/<car>/scan ("" = off)."""
    odom_topic: str = "/odom"
    """nav_msgs/msg/Odometry mirror of racecav/<car>/state ("" = off)."""
    drive_out_topic: str = "/drive_out"
    """ackermann_msgs/msg/AckermannDriveStamped mirror of racecav/<car>/cmd ("" = off). Not
    /drive: that name is the F1TENTH command input below, and a mirror must not feed it."""
    drive_in_topic: str = "/drive"
    """AckermannDriveStamped from ROS -> DriveCommand (source "ros") on racecav/<car>/drive_ros,
    below teleop in the actuator's mux ("" = no ROS command input)."""
    stamps: Literal["wall", "source"] = "wall"
    """Header stamps: wall = this host's real-time clock at mirroring (what ROS tools expect);
    source = the racecav stamp (sim time, or the car's monotonic clock)."""
    base_frame: str = "base_link"
    """The car's body frame: Odometry child_frame_id, AckermannDriveStamped frame_id."""
    car: str = "slash"
    """Car file: throttle model (speed <-> throttle) and steering limits."""
    nice: int = Field(10, ge=0, le=19)
    """Niceness added to the mirror process: on a busy CPU the controllers go first (measured in
    docs/benchmarks.md, record). Set 0 when a ROS controller drives the car through /drive."""
    max_payload_bytes: int = Field(1024, gt=0)
    """A ROS input (``/drive``) payload larger than this is refused before decoding and counted
    as invalid (an AckermannDriveStamped is ~60 bytes; the frame_id string is its only
    variable part)."""
    batch_s: float = Field(0.01, ge=0)
    """Outgoing messages are converted and sent in batches this often (s), not in the
    subscriber callback: the mirror's traffic then does not meet the scan -> command burst at
    the router (docs/benchmarks.md, record). 0 = at once."""


class VizConfig(Section):
    """The Foxglove view (``racecav viz``)."""

    host: str = "127.0.0.1"
    """Listen address of the Foxglove WebSocket server (0.0.0.0: reachable from the network)."""
    port: int = Field(8765, ge=0, le=65535)
    """WebSocket port (Foxglove's default 8765; 0 = any free port)."""
    world: str | None = None
    """World whose walls are drawn; None = the world of sim.scenario."""


class Config(Section):
    """The whole configuration. Sections are added by the services that own them."""

    bus: BusConfig = BusConfig()
    router: RouterConfig = RouterConfig()
    env: EnvConfig = EnvConfig()
    sensor: SensorConfig = SensorConfig()
    actuator: ActuatorConfig = ActuatorConfig()
    sim: SimConfig = SimConfig()
    policy: PolicyConfig = PolicyConfig()
    baseline: BaselineConfig = BaselineConfig()
    safety: SafetyConfig = SafetyConfig()
    ros2: Ros2Config = Ros2Config()
    viz: VizConfig = VizConfig()

    def digest(self) -> str:
        """Short hash of the effective configuration, reported in every ServiceStatus."""
        blob = json.dumps(self.model_dump(mode="json"), sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()[:12]


class ConfigError(Exception):
    """A configuration file or value is invalid; the message names the field."""


ENV_PREFIX = "RACECAV_"


def _env_overrides(environ: dict[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, raw in environ.items():
        if not name.startswith(ENV_PREFIX) or "__" not in name:
            continue
        path = name[len(ENV_PREFIX):].lower().split("__")
        try:
            value: Any = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        node = out
        for part in path[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{name}: conflicts with another RACECAV_ variable")
        node[path[-1]] = value
    return out


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(base.get(k), dict):
            _merge(base[k], v)
        else:
            base[k] = v
    return base


def load_config(path: str | Path | None = None, environ: dict[str, str] | None = None) -> Config:
    """Load defaults <- TOML file <- RACECAV_* variables, validated.

    :param path: TOML file, or None for defaults (``RACECAV_CONFIG`` names one too).
    :param environ: environment to read (default ``os.environ``).
    :raises ConfigError: naming the file and the first invalid field.
    """
    environ = dict(os.environ if environ is None else environ)
    path = path or environ.get("RACECAV_CONFIG")
    data: dict[str, Any] = {}
    if path:
        try:
            data = tomllib.loads(Path(path).read_text())
        except FileNotFoundError:
            raise ConfigError(f"config file {path}: not found") from None
        except IsADirectoryError:
            raise ConfigError(f"config file {path}: is a directory, not a TOML file") from None
        except UnicodeDecodeError as e:
            raise ConfigError(f"config file {path}: not UTF-8 text (byte {e.start})") from None
        except OSError as e:
            raise ConfigError(f"config file {path}: {e.strerror or e}") from None
        except tomllib.TOMLDecodeError as e:
            raise ConfigError(f"config file {path}: invalid TOML: {e}") from None
    env = _env_overrides(environ)
    data = _merge(data, env)
    try:
        return Config.model_validate(data)
    except ValidationError as e:
        def source(loc: tuple) -> str:  # the variable that set the field, else the file
            node = env
            for part in loc:
                if not isinstance(node, dict) or str(part) not in node:
                    break
                node = node[str(part)]
            else:
                if len(loc) < 2:  # a whole section's rule: no single variable set it
                    return f"{f'config file {path}' if path else 'configuration'}: {'.'.join(map(str, loc))}"
                return f"{ENV_PREFIX}{'__'.join(str(p).upper() for p in loc)} ({'.'.join(map(str, loc))})"
            return f"{f'config file {path}' if path else 'configuration'}: {'.'.join(map(str, loc))}"

        raise ConfigError(errors_line(e, source)) from None


def errors_line(e: ValidationError, name=lambda loc: ".".join(map(str, loc))) -> str:
    """A pydantic error as one line: ``<name(loc)>: <rule> (got <value>)`` per error, joined by
    "; " (no URL, no "Value error," prefix, no line breaks)."""
    parts = []
    for err in e.errors():
        msg = str(err["msg"]).removeprefix("Value error, ")
        value = err.get("input")
        got = repr(value)
        got = "" if isinstance(value, dict) and err["type"] == "value_error" else (  # a whole section
            f" (got {got if len(got) <= 60 else got[:57] + '...'})")
        parts.append(f"{name(tuple(err['loc']))}: {msg}{got}")
    return "; ".join(parts).replace("\n", " ")


def override(cfg: Config, section: str, values: dict[str, Any], flags: dict[str, str] | None = None) -> Config:
    """``cfg`` with command-line ``values`` (field -> value) applied to ``cfg.<section>``, validated.

    :param flags: field -> the option that set it, for the message.
    :raises ConfigError: one line naming the option and the field, e.g. ``--v-ref
        (baseline.v_ref): Input should be greater than or equal to 0 (got -1.0)``.
    """
    if not values:
        return cfg
    sec = getattr(cfg, section)
    flags = flags or {}

    def name(loc: tuple) -> str:
        field = ".".join(map(str, (section, *loc)))
        flag = flags.get(str(loc[0])) if loc else None
        return f"{flag} ({field})" if flag else field

    try:
        new = type(sec).model_validate({**sec.model_dump(), **values})
    except ValidationError as e:
        raise ConfigError(errors_line(e, name)) from None
    return cfg.model_copy(update={section: new})


def apply_options(cfg: Config, section: str, args, options: dict[str, str],
                  extra: dict[str, Any] | None = None) -> Config:
    """``cfg`` with a command's typed options applied to ``cfg.<section>`` (:func:`override`).

    :param options: option dest -> field (``{"v_ref": "v_ref", "max_scan_age": "max_scan_age_s"}``);
        the option is ``--`` + dest with '-' for '_'. Options left at None are not applied.
    :param extra: more field values (from flags without a value, e.g. ``--racetrack``).
    """
    values = {f: getattr(args, d) for d, f in options.items() if getattr(args, d, None) is not None}
    values.update(extra or {})
    return override(cfg, section, values, {f: "--" + d.replace("_", "-") for d, f in options.items()})
