"""``racecav sim``: the PyBullet world playing the car on the bus (hardware-in-the-loop stand-in).

It publishes what the real car's services publish, on the same keys: the agent's Scan
(``source = "sim"``, same format and preprocessing contract as the sensor service's), its
VehicleState and the ground-truth ObstacleStates; it consumes DriveCommand on the cmd key like
the actuator, using the command's physical throttle and steering angle.

Two modes (config section ``sim``):
- realtime: the world runs against the wall clock scaled by ``real_time_factor``; the newest
  command applies at the next physics substep after it arrives; a command is held at most
  ``watchdog_s`` (wall), then the car brakes (wheel speed target 0).
- lockstep: after publishing scan k the world waits for the command answering it
  (``scan_seq == k``); that command applies ``compute_ns`` into the next control period (the
  controller's measured compute latency: a slow controller still pays for its slowness). Same
  seed, same commands => same trajectory (``lockstep_compute_ms``: a fixed charge instead, for
  runs that repeat to the bit whatever the controller measures).

Inputs are arbitrated by the actuator's own mux (:class:`CommandMux`, actuator section: e-stop
latch > safety brake > teleop > ROS drive > controller, each with its timeout), so the sim and
the car obey the same order; the sim's cmd input accepts any controller and times out after
``watchdog_s``. Realtime: wall clock, like the actuator. Lockstep: sim time (a command counts
from its scan's time plus its compute time); with ``lockstep_safety`` each step also waits for
the safety supervisor's verdict on the scan (racecav/<car>/safety/verdict), so a brake always
applies to the scan it answers. A brake (neutral or the supervisor's) sets the wheel speed
target to 0.

Stamps are sim time (ns, monotonic across episodes); scan seq is monotonic across episodes.
Episodes are EPISODE_GAP_S apart in the stamps: a consumer that keeps history (the policy's scan
stack, which restarts on a gap of 1.5 scan periods) sees a reset as it sees a lost sensor,
instead of stacking the last scan of one world with the first of the next.
Queryables: racecav/<car>/sim/status, .../sim/reset (JSON {"seed": int?, "heading": str?}) and
.../sim/scenario (JSON {"name": NAME|FILE, "seed": int?}; no payload: current and available).
"""

from __future__ import annotations

import argparse
import json

from pydantic import ValidationError
import logging
import queue
import threading
import time
from typing import Any

from racecav.common import keys
from racecav.common.bus import Service
from racecav.common.config import Config, ConfigError, apply_options
from racecav.common.lidar import make_scan, published_scan
from racecav.common.messages import DriveCommand, Obstacle, ObstacleStates, VehicleState
from racecav.common.perturb import command_delay, trial_rng
from racecav.common.scenario import load_scenario, scenario_names
from racecav.common.vehicle import load_car
from racecav.services.actuator.control import CommandMux, Decision

log = logging.getLogger("racecav.sim")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", help="scenario name or TOML file (racetrack, racetrack-reversed, "
                   "right-to-left, head-to-head, left-to-right, or a path); default: sim.scenario")
    p.add_argument("--racetrack", action="store_true", help="shorthand for --scenario racetrack")
    p.add_argument("--mode", choices=["realtime", "lockstep"], help="default: sim.mode")
    p.add_argument("--real-time-factor", type=float, help="realtime mode: sim s per wall s (0 = max)")
    p.add_argument("--seed", type=int, help="seed of the first episode")
    p.add_argument("--heading", choices=["default", "reversed"], help="racetrack: agent heading")
    p.add_argument("--on-end", choices=["hold", "reset"], help="at contact / end of trial")
    p.add_argument("--lidar-all", action="store_true", help="cast the lidar for every car")
    p.add_argument("--perturb", metavar="PRESET|KEY=VALUE,...",
                   help="sim-to-real perturbations: a preset of common/data/perturbations.toml (s2-nominal, "
                        "s2-pessimistic, worn-car, slippery-floor, late-computer), key=value pairs of "
                        "sim.perturb, or both (docs/robustness.md); default: sim.perturb")


OPTIONS = {"scenario": "scenario", "mode": "mode", "real_time_factor": "real_time_factor", "seed": "seed",
           "heading": "heading", "on_end": "on_end"}
"""Typed options -> sim.<field> (validated as the config is: a bad one exits 2 naming both)."""
SECTION = "sim"


def sim_config(args: argparse.Namespace, cfg: Config):
    """cfg.sim with the command-line overrides applied (validated; ConfigError naming the option)."""
    extra: dict[str, Any] = {}
    if getattr(args, "racetrack", False):
        extra["scenario"] = "racetrack"
    if getattr(args, "lidar_all", False):
        extra["lidar_all"] = True
    if getattr(args, "perturb", None) is not None:
        from racecav.common.perturb import parse_text

        try:
            extra["perturb"] = parse_text(args.perturb)
        except ValueError as e:  # one line naming the unknown preset or key
            raise ConfigError(f"--{e}") from None
    out = apply_options(cfg, SECTION, args, OPTIONS, extra).sim
    if out.mode == "realtime" and out.perturb.timing():
        raise ConfigError("sim.perturb: scan_jitter_s, latency_s and actuator_delay_s are charged in sim time: "
                          "they need --mode lockstep")
    return out


def run(args: argparse.Namespace, cfg: Config) -> int:
    scfg = sim_config(args, cfg)  # a bad option: ConfigError, one line, exit 2 (racecav.cli)
    try:
        svc = SimService(cfg.model_copy(update={"sim": scfg}))
    except (ConfigError, ValueError) as e:
        print(f"racecav sim: {e}")
        return 2
    return svc.run()


MAX_SEED = 2**32 - 1
"""Seeds from queries are within [0, MAX_SEED] (numpy's legacy seed range): larger ones broke
every status reply until the next reset (the status carries the seed)."""
EPISODE_GAP_S = 1.0
"""Sim time (s) between the last stamp of an episode and the first of the next (module doc)."""


def query_object(payload: bytes, what: str, fields: set[str]) -> dict:
    """A query's JSON object payload with only ``fields``; ValueError naming what is wrong."""
    try:
        data = json.loads(payload) if payload else {}
    except (ValueError, RecursionError) as e:  # not UTF-8, not JSON, nested beyond the parser
        raise ValueError(f"{what}: payload is not JSON ({e})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{what}: payload must be a JSON object")
    unknown = set(data) - fields
    if unknown:
        raise ValueError(f"{what}: unknown field(s) {sorted(unknown)}")
    return data


def check_seed(data: dict, what: str) -> None:
    """``data["seed"]``, if present, is an integer (not a bool) in [0, MAX_SEED]."""
    if "seed" in data:
        seed = data["seed"]
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
            raise ValueError(f"{what}.seed: must be an integer in [0, {MAX_SEED}]")


class SimService(Service):
    """The sim service (see the module docstring)."""

    def __init__(self, cfg: Config):
        super().__init__(cfg, "sim")
        self.scfg = cfg.sim
        self.car_params = load_car(self.scfg.car)
        self.scenario_ref = self.scfg.scenario
        self.world = self._make_world(load_scenario(self.scenario_ref))
        self.seq = 0
        self.offset_ns = 0            # sim time of earlier episodes (stamps stay monotonic)
        self.episode = -1
        self.next_seed = self.scfg.seed
        self.requests: queue.Queue = queue.Queue()
        self.counters = {"watchdog_brakes": 0, "stale_commands": 0, "lockstep_republish": 0,
                         "overruns": 0, "safety_brakes": 0, "safety_verdict_timeouts": 0}
        self.mux = CommandMux.from_config(cfg.actuator, controller=None, timeout_s=self.scfg.watchdog_s)
        self._fed: dict[str, int] = {}
        self._dead: set[str] = set()
        """Sources whose liveliness token vanished: their commands are ignored until it returns
        (a command still in flight when its controller died must not drive again)."""
        self._safety_on = False
        self._judged = threading.Condition()
        self._judged_seq = -1
        self.last_source = ""
        self.pending: list[tuple[float, str, DriveCommand]] = []
        """Lockstep: mux offers (sim time s, input, command) due in a later period."""
        self._rtf_window: list[tuple[float, float]] = []
        self._info: dict[str, Any] = {}
        self._new_episode(self.next_seed)

    # ------------------------------------------------------------------ world and episodes
    def _make_world(self, scenario):
        from racecav.sim.bullet_world import BulletWorld  # pybullet: only when running

        spec = published_scan(self.car_params.lidar, self.scfg.scan)
        if self.scfg.lidar_range_max is not None:
            spec = type(spec).model_validate({**spec.model_dump(), "range_max": self.scfg.lidar_range_max})
        return BulletWorld(scenario, car=self.car_params, lidar_all=self.scfg.lidar_all, lidar=spec,
                           heading=self.scfg.heading if scenario.traffic else None, perturb=self.scfg.perturb)

    def _new_episode(self, seed: int, heading: str | None = None, world=None) -> None:
        """Start an episode (in ``world`` if given: a scenario request swaps the world here, after
        the stamps advanced past the old one's time, so they never go back)."""
        if self.episode >= 0:
            self.offset_ns += int(round((self.world.t + EPISODE_GAP_S) * 1e9))
        if world is not None:
            self.world.close()
            self.world = world
        opts = {"heading": heading} if heading and self.world.scenario.traffic else {}
        self.world.reset(seed=seed, options=opts)
        self._timing_rng = trial_rng(seed, stream=1)  # perturbed timing: a function of the seed only
        self.episode += 1
        self.seed = seed
        self.next_seed = (seed + 1) % (MAX_SEED + 1)
        self.done = False
        self.pending = []
        self.world.set_physical(0.0, 0.0, brake=False)
        self._wall0 = None
        self._applied_since = -1.0
        if hasattr(self, "mux"):
            self.mux.forget()  # nothing said in the last episode holds in this one (the e-stop does)
        self._next = None
        self._rtf_window = []
        self._episode_wall_ns = time.monotonic_ns()
        self.started = not (self.scfg.mode == "realtime" and self.scfg.wait_for_controller)

    def setup(self) -> None:
        self.pub_scan = self.publisher(self.topic(keys.SCAN))
        self.pub_state = self.publisher(self.topic(keys.STATE))
        self.pub_obs = self.publisher(self.topic(keys.OBSTACLES))
        self.cmd = self.inbox(self.topic(keys.CMD), DriveCommand)
        # the mux's other inputs (the cmd inbox above is its controller input)
        self.mux_in = {keys.CMD: self.cmd, **{c: self.inbox(self.topic(c), DriveCommand)
                                            for c in (keys.SAFETY, keys.TELEOP, keys.DRIVE_ROS)}}
        self.subscribe(self.topic(keys.ESTOP), None, self.mux.estop)
        self.subscribe(keys.service_key(self.car, "safety", "verdict"), None, self._on_verdict)
        self.watch_alive("*", self._on_alive)  # the actuator's fail-safe: a dead controller brakes at once
        self.queryable("reset", self._q_reset)
        self.queryable("scenario", self._q_scenario)
        self._publish()

    # ------------------------------------------------------------------ queryables
    def _request(self, kind: str, data: dict) -> dict:
        done = threading.Event()
        box: dict = {}
        self.requests.put((kind, data, done, box))
        if not done.wait(10.0):
            raise TimeoutError(f"{kind}: the sim loop did not answer within 10 s")
        if "error" in box:
            raise ValueError(box["error"])
        return box["reply"]

    def _q_reset(self, payload: bytes | None) -> dict:
        data = query_object(payload, "reset", {"seed", "heading"})
        check_seed(data, "reset")
        if data.get("heading") not in (None, "default", "reversed"):
            raise ValueError("reset.heading: must be default or reversed")
        return self._request("reset", data)

    def _q_scenario(self, payload: bytes | None) -> dict:
        if not payload:
            return {"scenario": self.world.scenario.name, "available": scenario_names()}
        data = query_object(payload, "scenario", {"name", "seed"})
        check_seed(data, "scenario")
        name = data.get("name")
        if not isinstance(name, str) or not name or len(name) > 256 or "\0" in name:
            raise ValueError("scenario.name: required (a scenario name or TOML path, at most 256 characters)")
        if "/" not in name and not name.endswith(".toml") and name not in scenario_names():
            raise ValueError(f"scenario.name: {name!r} is not one of {scenario_names()}")
        try:
            load_scenario(name)  # a broken file is refused here, naming the field
        except OSError as e:
            raise ValueError(f"scenario.name: {name}: {e.strerror or e}") from None
        return self._request("scenario", data)

    def _poll_requests(self) -> bool:
        """Serve queued reset/scenario requests; True if the episode changed."""
        changed = False
        while True:
            try:
                kind, data, done, box = self.requests.get_nowait()
            except queue.Empty:
                return changed
            try:
                new = None
                if kind == "scenario":
                    new = self._make_world(load_scenario(data["name"]))
                    self.scenario_ref = data["name"]
                self._new_episode(data.get("seed", self.next_seed), data.get("heading"), world=new)
                self._publish()
                # seq and stamp of the episode's first sample (a recorder cuts its files there)
                box["reply"] = {"episode": self.episode, "seed": self.seed,
                                "scenario": self.world.scenario.name, "seq": self.seq - 1,
                                "stamp_ns": self._stamp()}
                changed = True
            except Exception as e:  # reply with the error, keep running
                box["error"] = f"{kind}: {e}"
            finally:
                done.set()

    # ------------------------------------------------------------------ publishing
    def _stamp(self) -> int:
        return self.offset_ns + int(round(self.world.t * 1e9))

    def _publish(self) -> None:
        w, stamp = self.world, self._stamp()
        self.scan_seq = self.seq
        self.scan_t = w.t
        x, y, yaw, vx, vy, r = w.car_state(0)
        # the state first: whoever judges the scan (baseline, safety supervisor) already has the
        # state of the same instant (samples of one session through one router keep their order)
        self.pub_state.put(VehicleState(stamp_ns=stamp, seq=self.seq, source="sim", x=x, y=y, yaw=yaw,
                                        vx=vx, vy=vy, yaw_rate=r, steering_angle=float(w.steer[0]),
                                        collided=w.collided))
        self.pub_scan.put(make_scan(w.scan_ranges, stamp, self.seq, "sim", w.spec))
        if self.scfg.publish_obstacles:
            obs = [Obstacle(id=i + 1, x=o[0], y=o[1], yaw=o[2], speed=o[3], length=self.car_params.length,
                            width=self.car_params.width) for i, o in enumerate(w.obstacles()[0])]
            self.pub_obs.put(ObstacleStates(stamp_ns=stamp, seq=self.seq, obstacles=obs))
        self.seq += 1
        self._snapshot()

    def _snapshot(self) -> None:
        """Episode state for the status queryable, taken in the loop thread (PyBullet is not
        thread-safe: the queryable thread must never touch the world)."""
        w = self.world
        rtf = None
        if len(self._rtf_window) >= 2:
            (a, sa), (b, sb) = self._rtf_window[0], self._rtf_window[-1]
            rtf = (sb - sa) / (b - a) if b > a else None
        self._info = {"mode": self.scfg.mode, "lockstep_compute_ms": self.scfg.lockstep_compute_ms,
                      "perturb": self.scfg.perturb.text(),
                      "scenario": w.scenario.name, "world": w.world.name,
                      "heading": w.heading, "seed": self.seed, "episode": self.episode, "t": w.t,
                      "steps": w.steps, "done": self.done, "collided": w.collided,
                      "contact_with": w.contact_with, "progress_m": float(w.progress()[0]),
                      "success": bool(w.success()[0]),
                      "real_time_factor_target": self.scfg.real_time_factor, "real_time_factor": rtf,
                      "seq": self.seq - 1, "started": self.started}

    def _after_period(self) -> None:
        w = self.world
        if w.collided or w.t >= w.scenario.duration_s - 1e-9:
            self.done = True
            self.log.info("episode %d done at t=%.2f s: %s, progress %.2f m, success %s", self.episode,
                          w.t, w.contact_with or "time up", w.progress()[0], w.success()[0])
        self._publish()

    # ------------------------------------------------------------------ loop
    def step(self) -> None:
        self._poll_requests()
        if self.done:
            if self.scfg.on_end == "reset":
                self._new_episode(self.next_seed)
                self._publish()
            else:
                self.stop_event.wait(0.05)
            return
        if self.scfg.mode == "lockstep":
            self._step_lockstep()
        else:
            self._step_realtime()

    def _step_realtime(self) -> None:
        w, car = self.world, self.car_params
        if not self.started:
            deadline = time.monotonic() + 0.5
            while self.cmd.latest()[1] <= self._episode_wall_ns:
                if time.monotonic() > deadline:
                    self.seq -= 1  # nobody answered yet: the same first scan again
                    self._publish()
                    return
                if self.stop_event.wait(0.005) or not self.requests.empty():
                    return
            self.started = True
        rtf = self.scfg.real_time_factor
        dt = car.physics_dt
        if self._wall0 is None:
            self._wall0, self._sim0 = time.monotonic(), w.t
        w.begin_period()
        for _ in range(car.physics_substeps):
            t0 = w.t
            if rtf > 0:
                # simulate [t0, t0 + dt] once the wall clock has reached its end, so a command
                # that arrived inside it switches the actuators at its arrival time
                lag = time.monotonic() - (self._wall0 + (t0 + dt - self._sim0) / rtf)
                if lag < 0:
                    if self.stop_event.wait(-lag):
                        return
                elif lag > 0.5:  # far behind (slow machine, rtf too high): do not sprint to catch up
                    self.counters["overruns"] += 1
                    self._wall0, self._sim0 = time.monotonic() - dt / rtf, t0
            rel = self._apply_newest(t0, dt, rtf)
            if rel > 0:  # the new command arrived inside this step: old command until then
                w.actuate(rel)
                self._set_command()
            w.actuate(dt - rel)
            w.physics_step()
        w.end_period()
        self._rtf_window.append((time.monotonic(), w.t))
        self._rtf_window = self._rtf_window[-50:]
        self._after_period()

    def _on_verdict(self, raw: bytes) -> None:
        """The safety supervisor judged a scan (lockstep waits for it, see the module doc)."""
        try:
            seq = int(json.loads(raw)["scan_seq"])
        except (ValueError, KeyError, TypeError):
            self.invalid += 1
            return
        with self._judged:
            self._judged_seq = max(self._judged_seq, seq)
            self._judged.notify_all()

    def _feed_mux(self, when, skip: tuple[str, ...] = ()) -> list[tuple[float, str, DriveCommand]]:
        """Inputs that arrived since the last call, as (time, channel, command); ``when(msg,
        arrival_ns)`` gives the time in the mux's clock."""
        out = []
        for channel, box in self.mux_in.items():
            if channel in skip:
                continue
            msg, arrival = box.latest()
            if msg is not None and arrival != self._fed.get(channel):
                self._fed[channel] = arrival
                if msg.source in self._dead:
                    self.counters["from_lost_source"] = self.counters.get("from_lost_source", 0) + 1
                    continue
                out.append((when(msg, arrival), channel, msg))
        return out

    def _on_alive(self, name: str, alive: bool) -> None:
        """Liveliness callback: the controller whose command is in force died => drop it now
        (as the actuator does), not after watchdog_s."""
        if alive:
            self._dead.discard(name)
            return
        self._dead.add(name)
        cmd = self.cmd.latest()[0]
        if cmd is not None and cmd.source == name:
            self.mux.lost(keys.CMD)
            self.counters["controller_lost"] = self.counters.get("controller_lost", 0) + 1

    @staticmethod
    def _physical(d: Decision) -> tuple[float, float, bool]:
        """(throttle, steering angle, brake) for a mux decision."""
        if d.cmd is None:
            return 0.0, 0.0, True
        if d.brake:  # the safety supervisor's brake or a braking command, with its steering angle
            return 0.0, d.cmd.steering_angle, True
        return d.cmd.throttle, d.cmd.steering_angle, False

    def _apply_newest(self, t0: float, dt: float, rtf: float) -> float:
        """Pick the command for the physics step starting at sim time t0: returns the offset
        (s) into the step at which a newly arrived command takes over (0 = from the start). The
        command is applied by :meth:`_set_command` (now if the offset is 0)."""
        for t, channel, msg in self._feed_mux(lambda _m, arrival: arrival * 1e-9):
            self.mux.offer(msg, channel, t)
        d = self.mux.decide(time.monotonic())
        if d.cmd is None:
            if d.reason == "timeout" and not self.world.brake:
                self.counters["watchdog_brakes"] += 1
            self._next = None
            self.world.set_physical(0.0, 0.0, brake=True)
            return 0.0
        self._next = d
        rel = 0.0
        if d.since != self._applied_since:
            if rtf > 0:
                t_arrival = self._sim0 + (d.since - self._wall0) * rtf
                rel = min(max(t_arrival - t0, 0.0), dt)
            self._applied_since = d.since
        if rel == 0.0:
            self._set_command()
        return rel

    def _count_safety(self, d: Decision) -> None:
        if d.reason == "safety" and not self._safety_on:
            self.counters["safety_brakes"] += 1
        self._safety_on = d.reason == "safety"

    def _set_command(self) -> None:
        d = self._next
        self._count_safety(d)
        self.world.set_physical(*self._physical(d))
        self.last_source = d.cmd.source

    def _wait_verdict(self, seq: int) -> None:
        """Lockstep with a safety supervisor: wait until it judged scan ``seq``."""
        deadline = time.monotonic() + self.scfg.lockstep_timeout_s
        with self._judged:
            if not self._judged.wait_for(lambda: self._judged_seq >= seq or self.stop_event.is_set(),
                                         max(0.0, deadline - time.monotonic())):
                self.counters["safety_verdict_timeouts"] += 1

    def _step_lockstep(self) -> None:
        w = self.world
        want, t_k = self.scan_seq, self.scan_t
        waited = time.monotonic()
        while True:
            if self.stop_event.is_set():
                return
            if self._poll_requests():
                return  # a new episode started (its first scan is published)
            cmd = self.cmd.take(timeout=0.05)
            if cmd is not None:
                if cmd.scan_seq == want:
                    break
                self.counters["stale_commands"] += 1
            if time.monotonic() - waited > self.scfg.lockstep_timeout_s:
                self.counters["lockstep_republish"] += 1
                self.seq -= 1  # same scan again (a lost sample must not dead-lock the run)
                self._publish()
                waited = time.monotonic()
        if self.scfg.lockstep_safety:
            self._wait_verdict(want)

        # the mux runs on the episode's sim time (it forgot every input at the reset; the e-stop
        # latch outlives episodes): the same trial gives the same schedule to the last bit

        # perturbed timing (sim.perturb): the answer also waits for the scan's jitter, the extra
        # latency and the actuator delay; a delay past this period carries over (self.pending)
        extra = command_delay(self.scfg.perturb, self._timing_rng) if self.scfg.perturb.timing() else 0.0

        def when(msg: DriveCommand, _arrival: int) -> float:
            # an answer to this scan counts from the scan plus its compute time; other inputs
            # (teleop, ROS) from the start of this period
            if msg.scan_seq != want:
                return t_k
            fixed = self.scfg.lockstep_compute_ms
            return t_k + (msg.compute_ns * 1e-9 if fixed is None else fixed * 1e-3) + extra

        # the controller's input is its answer to this scan (taken above), not the newest sample
        new = [(when(cmd, 0), keys.CMD, cmd)]
        new += [e for e in self._feed_mux(when, skip=(keys.CMD,)) if e[1] != keys.SAFETY or e[2].scan_seq == want]
        self.pending.extend(sorted(new, key=lambda e: e[0]))
        end = t_k + self.car_params.control_period_s - 1e-12
        due = sorted((e for e in self.pending if e[0] < end), key=lambda e: e[0])
        self.pending = [e for e in self.pending if e[0] >= end]
        # walk the period: the mux's decision changes at each due offer and when an input expires
        schedule, prev, t, i = [], None, t_k, 0
        while True:
            while i < len(due) and due[i][0] <= t + 1e-12:
                self.mux.offer(due[i][2], due[i][1], due[i][0])
                i += 1
            d = self.mux.decide(t)
            self._count_safety(d)
            # before the episode's first command the car carries on as reset (the old behaviour)
            act = prev if d.reason == "no command" else self._physical(d)
            if act is not None and act != prev:
                schedule.append((max(t - t_k, 0.0), act))
                prev = act
            if d.cmd is not None:
                self.last_source = d.cmd.source
            nxt = min(due[i][0] if i < len(due) else end, d.deadline)
            if nxt >= end:
                break
            t = max(nxt, t + 1e-9)
        # the command in force at the period start carries on until a scheduled one switches
        w.step((float(w.throttle[0]), float(w.steer_target[0]), bool(w.brake)), schedule=schedule,
               physical=True)
        self._after_period()

    # ------------------------------------------------------------------ status
    def info(self) -> dict[str, Any]:
        return {**self._info, "last_source": self.last_source, **self.counters,
                "mux": {"estop": self.mux.estopped, "accepted_by": dict(self.mux.accepted_by),
                        "refused": self.mux.refused}}

    def teardown(self) -> None:
        self.world.close()
