"""The evaluation harness: trials run through the real processes over Zenoh.

A :class:`Harness` starts a router, ``racecav sim`` (lockstep or realtime, holding at the end of
each trial) and one controller service as separate processes, each a client of that router, then
runs trials through the sim's ``scenario`` and ``reset`` queryables with one seed per trial. A
:class:`Recorder` (a client session of the harness) listens to what is on the bus: the sim's
VehicleState and ObstacleStates (ground truth for the trajectory and the distances), the scans
and the commands (scan -> command latency on the router's clock, see :func:`_arrival`; the
controller's own ``compute_ns``). Outcome, contact and progress come from the sim's status
queryable at the end of the trial: the sim decides success exactly as in-process evaluation does.

Trial i of a run uses seed ``base_seed + i``: the same seed gives the same obstacle start,
speed and delay (Scenario.sample) whichever controller drives, and in lockstep mode the same
trajectory for the same commands.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import threading
import time
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from racecav.common import keys, procs, registry
from racecav.common.codec import DecodeError, decode
from racecav.common.config import Config
from racecav.common.messages import DriveCommand, ObstacleStates, Scan, VehicleState
from racecav.evaluation import metrics
from racecav.evaluation.results import Trajectory, Trial, stats


Controller = registry.ControllerSpec
"""A controller the harness runs: the registry's record with its weights file resolved."""


def _hold_speed_throttle(speed: float) -> float:
    """Throttle whose steady speed is ``speed`` for the sim's agent car."""
    from racecav.common.vehicle import load_car, throttle_for_speed

    car = load_car()
    return float(throttle_for_speed(speed, car, car.agent_speed_scale))


def _controller(spec: registry.ControllerSpec) -> Controller:
    """The registry's controller with its weights file and its scripted program resolved."""
    from racecav.common.policy import resolve_policy_path

    args = spec.args
    if "HOLD" in args:  # straight ahead at the throttle that holds HOLD_SPEED
        args = tuple(f"{_hold_speed_throttle(registry.HOLD_SPEED):.4f},0.0,100000000" if a == "HOLD" else a
                     for a in args)
    return dataclasses.replace(spec, args=args, model=resolve_policy_path(spec.policy) if spec.policy else None)


CONTROLLERS: dict[str, Controller] = {n: _controller(c) for n, c in registry.CONTROLLERS.items()}


def perturbed(ctrl: Controller, perturb) -> Controller:
    """``ctrl`` run under a perturbation (sim.perturb, common/perturb.py): its name, and so its
    results' run key and files, carry the perturbation's canonical text (NAME@key=value,...)."""
    text = perturb.text() if perturb is not None else "nominal"
    return ctrl if text == "nominal" else dataclasses.replace(ctrl, name=f"{ctrl.name}@{text}")


def missing(ctrl: Controller) -> str | None:
    """Why ``ctrl`` cannot run here (a missing service module or weights file), or None."""
    if importlib.util.find_spec(ctrl.module) is None:
        return f"the `racecav {ctrl.args[0]}` command ({ctrl.module}) is not installed"
    if ctrl.model is not None and not ctrl.model.exists():
        return f"the shipped weights {ctrl.model} do not exist yet"
    return None


def scan_kind(ctrl: Controller) -> str:
    """The scan the sim publishes for ``ctrl`` (SimConfig.scan): its policy's view, else paper."""
    if ctrl.model is None:
        return "paper"
    meta = Path(ctrl.model).with_suffix(".json")
    return json.loads(meta.read_text()).get("lidar", "paper") if meta.is_file() else "paper"


COMPUTE_CHARGES = ("fixed", "measured")
"""Lockstep compute charge: the registry's benchmarked charge_ms, or each command's compute_ns."""


class HarnessError(RuntimeError):
    """A trial could not run (a process died, the bus stopped answering...)."""


@dataclass
class _Cmd:
    scan_seq: int
    arrival: tuple[int | None, int]
    compute_ns: int


def _arrival(sample) -> tuple[int | None, int]:
    """(router timestamp in ns or None, local monotonic ns) of a sample.

    The router stamps every sample it routes (Zenoh timestamping, on by default in routers) with
    its hybrid logical clock: the difference of two such stamps is time at the router, free of
    this process's own scheduling delays.
    """
    local = time.monotonic_ns()
    ts = sample.timestamp
    return (None if ts is None else int(ts.get_time_as_ntp64().as_nanos())), local


def latency_ms(scan: tuple[int | None, int], cmd: tuple[int | None, int]) -> tuple[float, str] | None:
    """Scan -> command latency (ms) and the clock used ("router" or "harness"), or None when the
    command was seen before its scan (only possible on the harness's clock)."""
    if scan[0] is not None and cmd[0] is not None:
        return (cmd[0] - scan[0]) * 1e-6, "router"
    if cmd[1] >= scan[1]:
        return (cmd[1] - scan[1]) * 1e-6, "harness"
    return None


@dataclass
class Recorder:
    """What the harness sees on the bus, indexed by seq (sim seqs are monotonic across trials)."""

    session: object
    car: str = "car0"
    scans: dict[int, tuple[int | None, int]] = field(default_factory=dict)
    """scan seq -> arrival (router stamp, local monotonic ns) of its latest publication."""
    cmds: list[_Cmd] = field(default_factory=list)
    states: dict[int, VehicleState] = field(default_factory=dict)
    obstacles: dict[int, ObstacleStates] = field(default_factory=dict)
    bad: int = 0

    def __post_init__(self):
        self._cond = threading.Condition()
        s = self.session
        self._subs = [s.declare_subscriber(keys.topic(self.car, keys.SCAN), self._on_scan),
                      s.declare_subscriber(keys.topic(self.car, keys.CMD), self._on_cmd),
                      s.declare_subscriber(keys.topic(self.car, keys.STATE), self._on_state),
                      s.declare_subscriber(keys.topic(self.car, keys.OBSTACLES), self._on_obstacles)]

    def _decode(self, sample, cls):
        try:
            return decode(sample.payload.to_bytes(), cls)
        except DecodeError:
            self.bad += 1
            return None

    def _on_scan(self, sample) -> None:
        now = _arrival(sample)
        msg = self._decode(sample, Scan)
        if msg is not None:
            with self._cond:
                self.scans[msg.seq] = now

    def _on_cmd(self, sample) -> None:
        now = _arrival(sample)
        msg = self._decode(sample, DriveCommand)
        if msg is not None:
            with self._cond:
                self.cmds.append(_Cmd(msg.scan_seq, now, msg.compute_ns))

    def _on_state(self, sample) -> None:
        msg = self._decode(sample, VehicleState)
        if msg is not None:
            with self._cond:
                self.states[msg.seq] = msg
                self._cond.notify_all()

    def _on_obstacles(self, sample) -> None:
        msg = self._decode(sample, ObstacleStates)
        if msg is not None:
            with self._cond:
                self.obstacles[msg.seq] = msg
                self._cond.notify_all()

    def wait_for(self, pred, timeout: float) -> bool:
        """Wait until ``pred(self)`` holds (checked on each state/obstacle arrival)."""
        with self._cond:
            return self._cond.wait_for(lambda: pred(self), timeout)

    def take(self, first: int, last: int):
        """States, obstacles, scan arrivals and commands of seqs first..last; forget older ones."""
        with self._cond:
            states = [self.states[k] for k in range(first, last + 1) if k in self.states]
            obs = [self.obstacles.get(s.seq) for s in states]
            scans = {k: v for k, v in self.scans.items() if first <= k <= last}
            cmds = [c for c in self.cmds if first <= c.scan_seq <= last]
            for d in (self.states, self.obstacles, self.scans):
                for k in [k for k in d if k <= last]:
                    del d[k]
            self.cmds = [c for c in self.cmds if c.scan_seq > last]
        return states, obs, scans, cmds

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()


class Harness:
    """Router + sim + controller processes, and trials run through them (use as a context manager).

    :param controller: what to evaluate (a :data:`CONTROLLERS` entry).
    :param mode: sim mode: "lockstep" (deterministic, the controller's compute_ns is charged as
        latency) or "realtime" (wall clock, the command applies when it arrives).
    :param scenario: the first scenario (name or path), loaded when the sim starts.
    :param log_dir: where the processes' logs go.
    :param real_time_factor: realtime mode: sim seconds per wall second.
    :param record_dir: if set, a ``racecav record`` process writes one MCAP file per trial there
        (``<scenario>-<index>-seed<seed>.mcap``, cut at each episode's first stamp; what came
        before the first trial, the services coming up and the sim's start scenario: setup.mcap).
    :param safety: also run ``racecav safety`` (the emergency-brake supervisor; in lockstep the
        sim waits for its verdict on every scan, so its brakes are deterministic too).
    :param compute_charge: lockstep: "fixed" (default) charges every command the controller's
        benchmarked compute time (registry ``charge_ms``), so a trial repeats bit for bit whatever
        the machine's load; "measured" charges each command its own ``compute_ns``.
    :param perturb: the sim's sim-to-real perturbation (a PerturbConfig; None: cfg.sim.perturb).
    """

    def __init__(self, cfg: Config, controller: Controller, mode: str, scenario: str, log_dir: Path,
                 real_time_factor: float = 1.0, record_dir: Path | None = None, safety: bool = False,
                 compute_charge: str = "fixed", perturb=None):
        if compute_charge not in COMPUTE_CHARGES:
            raise ValueError(f"compute_charge: one of {COMPUTE_CHARGES}, not {compute_charge!r}")
        self.cfg, self.ctrl, self.mode, self.log_dir = cfg, controller, mode, Path(log_dir)
        self.charge_ms = controller.charge_ms if compute_charge == "fixed" and mode == "lockstep" else None
        """The compute time (ms) charged to every command; None: each command's own."""
        self.perturb = cfg.sim.perturb if perturb is None else perturb
        self.safety = safety
        self.record_dir = Path(record_dir) if record_dir is not None else None
        self.first_scenario, self.rtf = scenario, real_time_factor
        from racecav.common.vehicle import load_car

        self.car = load_car(cfg.sim.car)
        self.car_name = cfg.bus.car
        self.procs: dict[str, object] = {}
        self._stack = ExitStack()
        self.scenario_ref: str | None = None
        self.duration_s = self.route_m = 0.0

    # ------------------------------------------------------------------ processes
    def __enter__(self) -> "Harness":
        why = missing(self.ctrl)
        if why:
            raise HarnessError(f"cannot evaluate {self.ctrl.name}: {why}")
        self.log_dir.mkdir(parents=True, exist_ok=True)
        try:
            endpoint = self._stack.enter_context(procs.router(log_path=self.log_dir / "router.log"))
            from racecav.common.client import open_session
            from racecav.common.config import load_config

            self.session = open_session(load_config(environ={"RACECAV_BUS__CONNECT": f'["{endpoint}"]',
                                                             "RACECAV_BUS__CAR": self.car_name}))
            self._stack.callback(self.session.close)
            self.recorder = Recorder(self.session, self.car_name)
            self._stack.callback(self.recorder.close)
            env = procs.bus_env(endpoint, self.car_name, extra={
                "RACECAV_SIM__ON_END": "hold",
                # a scan the controller missed (it subscribed late) is republished soon
                "RACECAV_SIM__LOCKSTEP_TIMEOUT_S": "0.5",
                "RACECAV_SIM__REAL_TIME_FACTOR": str(self.rtf),
                # a wide-view policy needs the wide scan (it holds the paper's rays too)
                "RACECAV_SIM__SCAN": scan_kind(self.ctrl),
                "RACECAV_SIM__PERTURB": json.dumps(self.perturb.active())})
            if self.charge_ms is not None:
                env["RACECAV_SIM__LOCKSTEP_COMPUTE_MS"] = repr(float(self.charge_ms))
            if self.record_dir is not None:  # a separate process: the control path never waits for it
                # first: the start-up (and the sim's start scenario, run while the controller comes
                # up) always lands in setup.mcap, never in a trial's file, whatever the machine's load
                self.record_dir.mkdir(parents=True, exist_ok=True)
                self._start("record", ["record", "-o", str(self.record_dir / "setup.mcap")], env)
            if self.safety:  # before the sim: a lockstep sim waits for its verdicts
                env["RACECAV_SIM__LOCKSTEP_SAFETY"] = "true"
                self._start("safety", ["safety"], env)
            self._start("sim", ["sim", "--scenario", str(self.first_scenario), "--mode", self.mode], env)
            self._start(self.ctrl.service, list(self.ctrl.args), env)
        except BaseException:
            self._stack.close()
            raise
        return self

    def _start(self, service: str, args: list[str], env: dict) -> None:
        log = self.log_dir / f"{service}.log"
        p = procs.start(args, env, log)
        self.procs[service] = p
        self._stack.callback(procs.stop, p)
        try:
            procs.wait_alive(self.session, self.car_name, service, timeout=60, proc=p)
        except (RuntimeError, TimeoutError) as e:
            raise HarnessError(f"{service}: {e}\n{_tail(log)}") from None

    def __exit__(self, *exc) -> None:
        self._stack.close()  # controller, sim, recorder, session, router: reverse order

    def _check_procs(self) -> None:
        for name, p in self.procs.items():
            if p.poll() is not None:
                raise HarnessError(f"{name} exited with code {p.returncode}\n{_tail(self.log_dir / f'{name}.log')}")

    def status_info(self) -> dict:
        from racecav.common.client import get_status

        return get_status(self.session, self.car_name, "sim", timeout=5.0).info

    def controller_status(self):
        from racecav.common.client import get_status

        return get_status(self.session, self.car_name, self.ctrl.service, timeout=5.0)

    # ------------------------------------------------------------------ trials
    def set_scenario(self, ref: str) -> None:
        """Trials from now on use scenario ``ref`` (a name or a TOML path the sim can read)."""
        from racecav.common.scenario import load_scenario

        sc = load_scenario(ref)
        self.duration_s, self.route_m = sc.duration_s, sc.success.min_progress_m
        self.scenario_ref = ref
        self._need_scenario = True

    def run_trial(self, index: int, seed: int, keep_trajectory: bool = True) -> Trial:
        """Run one trial to its end (contact or the scenario's duration) and measure it."""
        from racecav.common.client import query_message

        if self.scenario_ref is None:
            raise HarnessError("set_scenario() first")
        self._check_procs()
        wall0 = time.monotonic()
        try:
            if self.record_dir is not None:  # this trial's samples go to their own file: the
                # recorder holds what comes from here on and cuts at the episode's first stamp
                name = f"{Path(self.scenario_ref).stem}-{index:03d}-seed{seed}.mcap"
                for attempt in range(50):  # alive (token) comes a moment before its queryables
                    try:
                        query_message(self.session, self.car_name, "record", "rotate",
                                      {"path": name, "hold": True}, timeout=10.0)
                        break
                    except RuntimeError:
                        if attempt == 49:
                            raise
                        time.sleep(0.1)
            if self._need_scenario:
                rep = query_message(self.session, self.car_name, "sim", "scenario",
                                    {"name": self.scenario_ref, "seed": seed}, timeout=30.0)
                self._need_scenario = False
            else:
                rep = query_message(self.session, self.car_name, "sim", "reset", {"seed": seed}, timeout=15.0)
            if self.record_dir is not None:
                query_message(self.session, self.car_name, "record", "release", {"stamp_ns": rep["stamp_ns"]},
                              timeout=10.0)
        except RuntimeError as e:
            self._check_procs()
            raise HarnessError(f"trial {index}: {e}") from None
        episode, first = rep["episode"], rep["seq"]
        n_steps = int(round(self.duration_s / self.car.control_period_s))
        # wall-time budget: realtime runs at rtf; lockstep at the speed of sim + controller
        budget = 60.0 + (self.duration_s / self.rtf if self.mode == "realtime" and self.rtf > 0 else 0.0) + 1.0 * n_steps
        deadline = time.monotonic() + budget

        period = self.car.control_period_s

        def ended(rec: Recorder) -> bool:
            # seq k of the episode is trial time (k - first) * period (republished scans and
            # states keep their seq), so a lost sample does not hide the end
            last = max(rec.states, default=-1)
            if last < first:
                return False
            return rec.states[last].collided or (last - first) * period >= self.duration_s - 1e-6

        def sim_done() -> dict | None:
            info = self.status_info()
            return info if info.get("episode") == episode and info.get("done") else None

        info = None
        while info is None:
            if self.recorder.wait_for(ended, timeout=0.5):
                # the sim's own verdict (its status is snapshotted right after the last state)
                for _ in range(100):
                    info = sim_done()
                    if info is not None:
                        break
                    time.sleep(0.01)
                else:
                    raise HarnessError(f"trial {index}: the sim never reported the episode done: "
                                       f"{self._safe_status()}")
            else:  # nothing new for 0.5 s: a lost last sample? a dead process? out of time?
                self._check_procs()
                info = sim_done()
                if info is None and time.monotonic() > deadline:
                    raise HarnessError(f"trial {index} (seed {seed}) did not end within {budget:.0f} s wall; "
                                       f"sim status {self._safe_status()}")
        last = int(info["seq"])
        self.recorder.wait_for(lambda r: last in r.states and last in r.obstacles, timeout=2.0)
        states, obs, scans, cmds = self.recorder.take(first, last)
        return self._measure(index, seed, info, states, obs, scans, cmds, time.monotonic() - wall0,
                             keep_trajectory)

    def _safe_status(self) -> dict | str:
        try:
            return self.status_info()
        except Exception as e:  # the status is only for the error message
            return str(e)

    def _measure(self, index, seed, info, states, obs, scans, cmds, wall_s, keep) -> Trial:
        if not states:
            raise HarnessError(f"trial {index}: no VehicleState received from the sim")
        t0 = states[0].stamp_ns
        t = np.array([(s.stamp_ns - t0) * 1e-9 for s in states])
        ego = np.array([(s.x, s.y, s.yaw) for s in states])
        # a lost ObstacleStates sample (rare) takes its neighbour's value
        filled, prev = [], next((o for o in obs if o is not None), None)
        for o in obs:
            prev = o if o is not None else prev
            filled.append(prev)
        n_obs = min((len(o.obstacles) for o in filled if o is not None), default=0)
        tracks, gaps, centres, moving, sizes = [], [], [], [], []
        for k in range(n_obs):
            tr4 = np.array([(o.obstacles[k].x, o.obstacles[k].y, o.obstacles[k].yaw, o.obstacles[k].speed)
                            for o in filled])
            tr = tr4[:, :3]
            ob = filled[0].obstacles[k]
            tracks.append(tr)
            moving.append(tr4)
            sizes.append((ob.length, ob.width))
            ca = metrics.box_corners(ego[:, 0], ego[:, 1], ego[:, 2], self.car.length, self.car.width)
            cb = metrics.box_corners(tr[:, 0], tr[:, 1], tr[:, 2], ob.length, ob.width)
            gaps.append(metrics.footprint_gap(ca, cb).min())
            centres.append(np.hypot(ego[:, 0] - tr[:, 0], ego[:, 1] - tr[:, 1]).min())
        measured = [m for c in cmds if c.scan_seq in scans and (m := latency_ms(scans[c.scan_seq], c.arrival))]
        latency = [m[0] for m in measured]
        clocks = sorted({m[1] for m in measured})
        compute = [c.compute_ns * 1e-6 for c in cmds]
        traj = None
        if keep:
            r = lambda a: [tuple(round(float(v), 4) for v in row) for row in a]  # noqa: E731
            traj = Trajectory(t=[round(float(v), 4) for v in t], ego=r(ego), obstacles=[r(tr) for tr in tracks])
        collided = bool(info["collided"])
        c, s_ = np.cos(ego[:, 2]), np.sin(ego[:, 2])
        body = np.array([(st.vx, st.vy) for st in states])
        velocity = np.stack([c * body[:, 0] - s_ * body[:, 1], s_ * body[:, 0] + c * body[:, 1]], -1)
        measures = metrics.trial_measures(t, ego, velocity, moving, sizes, (self.car.length, self.car.width),
                                          collided, str(info.get("contact_with") or ""),
                                          float(info["progress_m"]), self.route_m, bool(info["success"]))
        return Trial(index=index, seed=seed, success=bool(info["success"]), collided=collided,
                     contact_with=str(info.get("contact_with") or ""),
                     contact_time_s=float(info["t"]) if collided else None, end_time_s=float(info["t"]),
                     progress_m=float(info["progress_m"]),
                     min_gap_m=float(min(gaps)) if gaps else None,
                     min_center_distance_m=float(min(centres)) if centres else None,
                     steps=len(states), commands=len(cmds), latency_ms=stats(latency),
                     compute_ms=stats(compute), wall_s=wall_s,
                     latency_clock="+".join(clocks) or "none", latency_steps_ms=[round(v, 4) for v in latency],
                     compute_steps_ms=[round(v, 4) for v in compute], trajectory=traj, measures=measures)


def _tail(path: Path, n: int = 15) -> str:
    try:
        lines = Path(path).read_text(errors="replace").splitlines()[-n:]
    except OSError:
        return ""
    return f"--- last lines of {path} ---\n" + "\n".join(lines)
