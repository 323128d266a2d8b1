"""``racecav bench faults``: the reliability figures of docs/reliability.md, measured with real
processes (router, actuator, controller, sim, policy, baseline, safety; the VESC and RPLIDAR
emulators on ptys).

- kill -> brake: a 10 Hz controller process is SIGKILLed while driving; time until the VESC
  emulator receives the brake frame (liveliness fail-safe; and, for reference, with
  ``actuator.follow_liveliness = false``, the timeout alone);
- soak: a live 10 Hz controller drives for ``--soak-s`` seconds: brake frames (spurious brakes);
- e-stop: put -> brake latency; the latch across a kill -9 + restart of the actuator; an e-stop
  published while the actuator is down;
- lidar: replug -> first revolution with the shipped timings; garbage-only stream -> reset, and
  -> scans again; a health error -> scans again;
- router: SIGKILL, outage, restart on the same port -> first command through it;
- fuzz: ``--fuzz-per-key`` hostile payloads on every input key (common/fuzz.py): services alive,
  every payload counted, exceptions (``errors``), RSS before/after.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from racecav.common import keys, procs
from racecav.common.bench import dump_json, machine, summarize, table

DOC = Path("docs/reliability.md")
CAR = "car0"

CONTROLLER = r"""
import sys, time
from racecav.common import keys
from racecav.common.bus import Service
from racecav.common.config import load_config
from racecav.common.messages import DriveCommand

class Ctrl(Service):
    def setup(self):
        self.pub = self.publisher(self.topic(keys.CMD), command=True)
        self.k = 0
        self.next = time.monotonic()
    def step(self):
        self.pub.put(DriveCommand(stamp_ns=time.monotonic_ns(), seq=self.k, source="policy", a_throttle=0.4,
                                  a_steer=0.1, throttle=0.4, steering_angle=0.05))
        self.k += 1
        self.next += float(sys.argv[1])
        self.stop_event.wait(max(0.0, self.next - time.monotonic()))

Ctrl(load_config(), "policy").run()
"""
"""A minimal controller process: service "policy" (liveliness token) commanding at a fixed period."""


def start_controller(endpoint: str, period_s: float = 0.1) -> subprocess.Popen:
    return procs.track(subprocess.Popen([sys.executable, "-c", CONTROLLER, str(period_s)],
                                        env=procs.bus_env(endpoint), start_new_session=True,
                                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))


def _wait(pred, timeout: float, step: float = 0.002) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(step)
    return False


def _session(endpoint: str):
    from racecav.common.client import open_session
    from racecav.common.config import load_config

    return open_session(load_config(environ={"RACECAV_BUS__CONNECT": f'["{endpoint}"]'}))


def _status(session, name: str, attempts: int = 5):
    """A service's status, retried: a service that just (re)started, or one still working
    through a flood, answers late rather than never."""
    from racecav.common.client import get_status

    for attempt in range(attempts):
        try:
            return get_status(session, CAR, name, timeout=5)
        except RuntimeError as e:
            if attempt == attempts - 1:
                raise RuntimeError(f"{name} does not answer its status: {e}") from None
            time.sleep(0.5)


def _kill(p: subprocess.Popen) -> None:
    os.killpg(p.pid, signal.SIGKILL)
    p.wait()


class Rig:
    """Router + VESC emulator + actuator (+ a client session) in a temporary directory."""

    def __init__(self, stack: ExitStack, tmp: Path, **actuator_env: str):
        from racecav.services.actuator.emulator import VescEmulator

        self.tmp, self.stack = tmp, stack
        self.endpoint = stack.enter_context(procs.router(log_path=tmp / "router.log"))
        self.vesc = VescEmulator(link=tmp / "vesc").start()
        stack.callback(self.vesc.stop)
        self.session = _session(self.endpoint)
        stack.callback(self.session.close)
        self.env = {"RACECAV_ACTUATOR__STATE_DIR": str(tmp / "state"),
                    **{f"RACECAV_ACTUATOR__{k.upper()}": v for k, v in actuator_env.items()}}
        self.actuator = self.start_actuator()

    def start_actuator(self) -> subprocess.Popen:
        p = procs.start(["actuator", "--port", self.vesc.path], procs.bus_env(self.endpoint, extra=self.env),
                        self.tmp / "actuator.log")
        self.stack.callback(procs.stop, p)
        procs.wait_alive(self.session, CAR, "actuator", proc=p)
        _wait(lambda: self.vesc.frames("SET_CURRENT_BRAKE"), 5)
        return p

    def rpm_after(self, t: float) -> list:
        return [r for r in self.vesc.frames("SET_RPM") if r.t > t]

    def brakes_after(self, t: float) -> list:
        return [r for r in self.vesc.frames("SET_CURRENT_BRAKE") if r.t > t]


# --- measurements -------------------------------------------------------------------------------

def measure_kill_to_brake(kills: int, follow_liveliness: bool = True) -> list[float]:
    """Seconds from SIGKILL of a driving 10 Hz controller to the brake frame at the VESC."""
    delays = []
    with tempfile.TemporaryDirectory() as tmp, ExitStack() as stack:  # processes stop first
        rig = Rig(stack, Path(tmp), FOLLOW_LIVELINESS=str(follow_liveliness).lower())
        for _ in range(kills):
            ctrl = start_controller(rig.endpoint)
            try:
                t0 = time.monotonic()
                if not _wait(lambda: rig.rpm_after(t0), 20):
                    raise RuntimeError("the controller never drove")
                time.sleep(0.5)
                t_kill = time.monotonic()
                _kill(ctrl)
                if _wait(lambda: rig.brakes_after(t_kill), 2):
                    delays.append(rig.brakes_after(t_kill)[0].t - t_kill)
            finally:
                procs.stop(ctrl)
    return delays


def measure_soak(seconds: float, period_s: float = 0.1) -> dict:
    """A live controller at 1/period_s Hz for ``seconds``: brake frames received meanwhile."""
    with tempfile.TemporaryDirectory() as tmp, ExitStack() as stack:  # processes stop first
        rig = Rig(stack, Path(tmp))
        ctrl = start_controller(rig.endpoint, period_s)
        stack.callback(procs.stop, ctrl)
        arrivals: list[float] = []  # the controller's commands as the bus delivers them
        sub = rig.session.declare_subscriber(keys.topic(CAR, keys.CMD), lambda _s: arrivals.append(time.monotonic()))
        stack.callback(sub.undeclare)
        t0 = time.monotonic()
        if not _wait(lambda: rig.rpm_after(t0), 20):
            raise RuntimeError("the controller never drove")
        t_start = rig.rpm_after(t0)[0].t + 0.5
        time.sleep(seconds + 0.5)
        t_end = time.monotonic()
        brakes = [r.t for r in rig.brakes_after(t_start) if r.t < t_end]
        episodes = sum(1 for i, t in enumerate(brakes) if i == 0 or t - brakes[i - 1] > 0.05)
        rpm = [r for r in rig.rpm_after(t_start) if r.t < t_end]
        gaps = np.diff([t for t in arrivals if t_start <= t < t_end])
    from racecav.common.config import ActuatorConfig

    timeout = ActuatorConfig().timeout_s
    # why a brake happened: a command gap longer than the timeout is the controller (or the box)
    # being late, not the actuator
    return {"seconds": round(t_end - t_start, 1), "rpm_frames": len(rpm), "brake_frames": len(brakes),
            "brake_episodes": episodes, "load_avg_5min": round(os.getloadavg()[1], 2),
            "cmd_gap_p99_ms": round(float(np.percentile(gaps, 99)) * 1e3, 1) if len(gaps) else None,
            "cmd_gap_max_ms": round(float(gaps.max()) * 1e3, 1) if len(gaps) else None,
            "cmd_gaps_over_timeout": int((gaps > timeout).sum()), "timeout_s": timeout}


def measure_estop(n: int) -> dict:
    """E-stop put -> brake latency (n times), then the latch across kill -9 + restart and an
    e-stop published while the actuator is down."""
    from racecav.common.codec import encode
    from racecav.common.messages import DriveCommand

    def cmd(k):
        return encode(DriveCommand(stamp_ns=time.monotonic_ns(), seq=k, source="policy", a_throttle=0.5,
                                   a_steer=0.0, throttle=0.5, steering_angle=0.0))

    lat = []
    out: dict = {}
    with tempfile.TemporaryDirectory() as tmp, ExitStack() as stack:  # processes stop first
        rig = Rig(stack, Path(tmp))
        pub = rig.session.declare_publisher(keys.topic(CAR, keys.CMD), express=True)
        estop = keys.topic(CAR, keys.ESTOP)
        stop = threading.Event()

        def drive():
            k = 0
            while not stop.is_set():
                pub.put(cmd(k))
                k += 1
                time.sleep(0.02)

        th = threading.Thread(target=drive, daemon=True)
        th.start()
        try:
            for _ in range(n):
                t0 = time.monotonic()
                _wait(lambda: rig.rpm_after(t0), 5)
                t_put = time.monotonic()
                rig.session.put(estop, b"stop")
                if _wait(lambda: rig.brakes_after(t_put), 2):
                    lat.append(rig.brakes_after(t_put)[0].t - t_put)
                rig.session.put(estop, b"clear")
                time.sleep(0.1)
            # latched, kill -9, restart while commands flow
            rig.session.put(estop, b"stop")
            time.sleep(0.2)
            _kill(rig.actuator)
            t_restart = time.monotonic()
            rig.actuator = rig.start_actuator()
            time.sleep(1.0)
            out["latched_after_restart"] = not rig.rpm_after(t_restart) and \
                _status(rig.session, "actuator").info["estop"] is True
            rig.session.put(estop, b" clear\n")
            time.sleep(0.3)
            out["near_clear_ignored"] = not rig.rpm_after(t_restart)
            rig.session.put(estop, b"clear")
            t_clear = time.monotonic()
            out["clear_drives"] = _wait(lambda: rig.rpm_after(t_clear), 2)
            # e-stop while the actuator is down; its latch file is removed too (a fresh car)
            _kill(rig.actuator)
            rig.session.put(estop, b"stop")
            for f in (Path(tmp) / "state").glob("estop-*.json"):
                f.unlink()
            t_restart = time.monotonic()
            rig.actuator = rig.start_actuator()
            time.sleep(1.0)
            out["estop_while_down_holds"] = not rig.rpm_after(t_restart)
            rig.session.put(estop, b"clear")
        finally:
            stop.set()
            th.join()
            pub.undeclare()
    out["latency_s"] = lat
    return out


def measure_lidar(replugs: int, garbage: int) -> dict:
    """On the emulator (0.1 s boot after RESET), with the shipped timings: replug -> first
    revolution; garbage-only stream -> reset, and its end -> first revolution; a 0.5 s health
    error (the device stops scanning) -> first revolution after it ends."""
    from racecav.common.config import SensorConfig
    from racecav.services.sensor import rplidar_protocol as rp
    from racecav.services.sensor.emulator import RplidarEmulator
    from racecav.services.sensor.rplidar_driver import RplidarDriver

    class GarbageEmulator(RplidarEmulator):
        garbage_only = False

        def _unit(self, mode, per_unit):
            data = super()._unit(mode, per_unit)
            if self.garbage_only:
                return (self.rng.integers(0, 256, len(data), dtype=np.uint8) & 0x3F).tobytes()
            return data

    c = SensorConfig()
    out: dict = {"replug_s": [], "garbage_reset_s": [], "garbage_recover_s": [], "health_recover_s": [],
                 "data_timeout_s": c.data_timeout_s, "silence_timeout_s": c.silence_timeout_s,
                 "reset_wait_s": c.reset_wait_s, "emulator_boot_s": 0.1}

    def first_after(t: float) -> float | None:
        return min(x for x in revs if x > t) - t if _wait(lambda: revs[-1] > t, 5) else None

    with tempfile.TemporaryDirectory() as tmp:
        emu = GarbageEmulator(link=Path(tmp) / "rplidar", reset_s=0.1).start()
        revs: list = []
        drv = RplidarDriver(emu.path, lambda r: revs.append(time.monotonic()), **c.driver_timings())
        th = drv.start_thread()
        try:
            if not _wait(lambda: revs, 10):
                raise RuntimeError(f"no revolution from the emulator: {drv.status()}")
            for _ in range(replugs):
                plugs = emu.plug_count
                emu.unplug(0.5)
                _wait(lambda: emu.plug_count > plugs and emu.link.exists(), 5)
                t_plug = time.monotonic()
                if (d := first_after(t_plug)) is not None:
                    out["replug_s"].append(d)
            for _ in range(garbage):
                _wait(lambda: revs[-1] > time.monotonic() - 0.3, 8)
                restarts = drv.stats.restarts
                emu.garbage_only = True
                t0 = time.monotonic()
                reset = _wait(lambda: drv.stats.restarts > restarts, 5)
                emu.garbage_only = False  # the fault ends at the reset
                t_end = time.monotonic()
                if reset:
                    out["garbage_reset_s"].append(t_end - t0)
                    if (d := first_after(t_end)) is not None:
                        out["garbage_recover_s"].append(d)
            for _ in range(garbage):
                _wait(lambda: revs[-1] > time.monotonic() - 0.3, 8)
                emu.set_health(rp.HEALTH_ERROR, 0x8003)  # stops the scan, like a protection stop
                time.sleep(0.5)
                emu.set_health(rp.HEALTH_OK)
                if (d := first_after(time.monotonic())) is not None:
                    out["health_recover_s"].append(d)
        finally:
            drv.stop_event.set()
            th.join(3)
            emu.stop()
    return out


def measure_router_restart(outages: list[float], bus_env: dict[str, str] | None = None) -> list[float]:
    """For each outage: SIGKILL the router, wait, restart it on the same port; seconds from the
    port accepting connections again to the first command crossing it (publisher and
    subscriber are two client sessions with the bus config's reconnect settings)."""
    import zenoh

    from racecav.common.bus import zenoh_config
    from racecav.common.config import load_config

    port = procs.free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    cfg = load_config(environ={"RACECAV_BUS__CONNECT": f'["{endpoint}"]', **(bus_env or {})})
    router, _ = procs.start_router(port)
    got: list[float] = []
    delays = []
    stop = threading.Event()
    with zenoh.open(zenoh_config(cfg.bus)) as sub_s, zenoh.open(zenoh_config(cfg.bus)) as pub_s:
        sub = sub_s.declare_subscriber(keys.topic(CAR, keys.CMD), lambda _s: got.append(time.monotonic()))
        pub = pub_s.declare_publisher(keys.topic(CAR, keys.CMD), express=True)

        def loop():
            while not stop.is_set():
                pub.put(b"cmd")
                time.sleep(0.01)

        th = threading.Thread(target=loop, daemon=True)
        th.start()
        try:
            _wait(lambda: got, 10)
            for outage in outages:
                _kill(router)
                time.sleep(outage)
                env = procs.bus_env(endpoint, extra={"RACECAV_ROUTER__LISTEN": f'["{endpoint}"]'})
                router = procs.start(["router"], env)
                while True:
                    try:
                        socket.create_connection(("127.0.0.1", port), timeout=0.1).close()
                        break
                    except OSError:
                        if router.poll() is not None:
                            raise RuntimeError("router did not restart") from None
                        time.sleep(0.002)
                t_listen = time.monotonic()
                if _wait(lambda: got[-1] > t_listen, 10):
                    delays.append(min(t for t in got if t > t_listen) - t_listen)
                time.sleep(0.3)
        finally:
            stop.set()
            th.join()
            sub.undeclare()
            pub.undeclare()
            procs.stop(router)
    return delays


def _rss_kb(pid: int) -> int:
    try:
        for line in open(f"/proc/{pid}/status"):
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


SUBSCRIBERS = {
    "actuator": [keys.CMD, keys.TELEOP, keys.SAFETY, keys.DRIVE_ROS, keys.ESTOP],
    "policy": [keys.SCAN],
    "baseline": [keys.SCAN, keys.STATE],
    "safety": [keys.SCAN, keys.CMD, keys.STATE],
    "sim": [keys.CMD, keys.TELEOP, keys.SAFETY, keys.DRIVE_ROS, keys.ESTOP, "safety/verdict"],
    "router": [keys.ESTOP],
    "ros2": [keys.SCAN, keys.STATE, keys.CMD, "ros2:/drive"],
}
"""Input keys of each service (their setup(); ``ros2:/drive``: the mirror's ROS 2 /drive input,
AckermannDriveStamped CDR on its rmw_zenoh key); the fuzz's expected counts come from this."""


def fuzz_services(per_key: int, warmup: int = 300, seed: int = 0, progress=None) -> dict:
    """Hostile payloads on every input key with the whole stack running; per service: alive,
    received / invalid deltas against what was sent, errors, RSS before and after."""
    import zenoh

    from racecav.common import fuzz
    from racecav.common.client import live_services
    from racecav.services.ros2 import fuzz as ros2_fuzz
    from racecav.common.config import load_config
    from racecav.services.actuator.emulator import VescEmulator

    rng = np.random.default_rng(seed)
    sent: Counter = Counter()
    invalid: Counter = Counter()
    with tempfile.TemporaryDirectory() as tmp, ExitStack() as stack:  # processes stop first
        tmp = Path(tmp)
        endpoint = stack.enter_context(procs.router(log_path=tmp / "router.log"))
        vesc = VescEmulator(link=tmp / "vesc").start()
        stack.callback(vesc.stop)
        session = _session(endpoint)
        stack.callback(session.close)
        env = procs.bus_env(endpoint, extra={"RACECAV_BASELINE__COMPILE": "false",
                                             "RACECAV_SIM__WAIT_FOR_CONTROLLER": "false",
                                             "RACECAV_ACTUATOR__STATE_DIR": str(tmp / "state")})
        started = {"actuator": ["actuator", "--port", vesc.path], "policy": ["policy"], "baseline": ["baseline"],
                   "safety": ["safety"], "sim": ["sim"], "ros2": ["ros2"]}
        for name, args in started.items():
            p = procs.start(args, env, tmp / f"{name}.log")
            stack.callback(procs.stop, p)
            procs.wait_alive(session, CAR, name, timeout=90, proc=p)
        # the mirror declares its ROS /drive subscriber in setup(), after its liveliness token
        if not _wait(lambda: "/drive" in _status(session, "ros2").info.get("keys", {}), 30, 0.2):
            raise RuntimeError("racecav ros2 has no /drive input")
        drive_key = _status(session, "ros2").info["keys"]["/drive"]
        max_drive = load_config().ros2.max_payload_bytes
        inputs = {leaf: (keys.topic(CAR, leaf), lambda leaf=leaf: fuzz.random_payload(leaf, rng),
                         lambda p, leaf=leaf: fuzz.expected_invalid(leaf, p)) for leaf in fuzz.INPUTS}
        inputs[ros2_fuzz.DRIVE_IN] = (drive_key, lambda: ros2_fuzz.random_drive_payload(rng, max_drive),
                                 lambda p: ros2_fuzz.drive_invalid(p, max_drive))

        def send(n: int, count: bool) -> None:
            for leaf, (key, make, is_invalid) in inputs.items():
                for _ in range(n):
                    payload = make()
                    session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
                    if count:
                        sent[leaf] += 1
                        invalid[leaf] += is_invalid(payload)
                    if progress is not None:
                        progress.update(1)
                    time.sleep(0.0002)

        send(warmup, False)
        time.sleep(1.0)
        before = {n: _status(session, n) for n in SUBSCRIBERS}
        rss0 = {n: _rss_kb(s.pid) for n, s in before.items()}
        t0 = time.monotonic()
        send(per_key // 2, True)
        rss_mid = {n: _rss_kb(s.pid) for n, s in before.items()}
        send(per_key - per_key // 2, True)
        elapsed = time.monotonic() - t0
        time.sleep(1.0)
        after = {n: _status(session, n) for n in SUBSCRIBERS}
        alive = live_services(session, CAR)
        rows = {}
        for name, st in after.items():
            rows[name] = {
                "alive": name in alive and st.pid == before[name].pid,
                "sent": sum(sent[k] for k in SUBSCRIBERS[name]),
                "received": st.received - before[name].received,
                "expected_invalid": sum(invalid[k] for k in SUBSCRIBERS[name]),
                "invalid": st.invalid - before[name].invalid,
                "errors": st.errors - before[name].errors,
                "rss_before_mb": round(rss0[name] / 1024, 1), "rss_mid_mb": round(rss_mid[name] / 1024, 1),
                "rss_after_mb": round(_rss_kb(st.pid) / 1024, 1)}
    return {"per_key": per_key, "keys": len(inputs), "sent_by_key": dict(sent),
            "invalid_by_key": dict(invalid), "seconds": round(elapsed, 1), "services": rows}


# --- the command --------------------------------------------------------------------------------

def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--kills", type=int, default=20, help="controller kill -9 -> brake measurements")
    p.add_argument("--soak-s", type=float, default=600.0, help="normal 10 Hz driving, counting spurious brakes")
    p.add_argument("--fuzz-per-key", type=int, default=10_000, help="hostile payloads per input key")
    p.add_argument("--estops", type=int, default=10, help="e-stop latency measurements")
    p.add_argument("--replugs", type=int, default=10, help="lidar unplug/replug cycles")
    p.add_argument("--restarts", type=int, default=5, help="router restarts per outage length")
    p.add_argument("--doc", type=Path, default=DOC, help="the report to write")


def _ms(s: dict, key: str = "median") -> str:
    return f"{s[key] * 1e3:.1f}" if s.get("n") else "n/a"


def run(args: argparse.Namespace, cfg=None) -> int:
    from tqdm import tqdm

    from racecav.common import fuzz

    res: dict = {}
    steps = ["kill -> brake", "timeout only", "soak", "e-stop", "lidar", "router", "fuzz"]
    with tqdm(total=len(steps), desc="faults", unit="part") as bar:
        bar.set_postfix_str(steps[0])
        res["kill_to_brake_s"] = measure_kill_to_brake(args.kills)
        bar.update(1)
        bar.set_postfix_str(steps[1])
        res["kill_to_brake_timeout_only_s"] = measure_kill_to_brake(max(3, args.kills // 4), follow_liveliness=False)
        bar.update(1)
        bar.set_postfix_str(steps[2])
        res["soak"] = measure_soak(args.soak_s) if args.soak_s > 0 else {}
        bar.update(1)
        bar.set_postfix_str(steps[3])
        res["estop"] = measure_estop(args.estops)
        bar.update(1)
        bar.set_postfix_str(steps[4])
        res["lidar"] = measure_lidar(args.replugs, max(1, args.replugs // 2))
        bar.update(1)
        bar.set_postfix_str(steps[5])
        res["router_restart_s"] = {str(o): measure_router_restart([o] * args.restarts) for o in (0.5, 2.0)}
        bar.update(1)
        bar.set_postfix_str(steps[6])
        with tqdm(total=(args.fuzz_per_key + 300) * (len(fuzz.INPUTS) + 1), desc="fuzz payloads", leave=False) as fbar:
            res["fuzz"] = fuzz_services(args.fuzz_per_key, progress=fbar) if args.fuzz_per_key > 0 else {}
        bar.update(1)
    command = "racecav bench faults" + (" " + " ".join(sys.argv[3:]) if len(sys.argv) > 3 else "")
    dump_json(getattr(args, "json", None), res)
    if not getattr(args, "no_doc", False):
        args.doc.parent.mkdir(parents=True, exist_ok=True)
        args.doc.write_text(report(res, command))
        print(f"wrote {args.doc}")
    print(json.dumps({k: v for k, v in res.items() if k != "fuzz"}, indent=1, default=str)[:3000])
    return 0


def report(res: dict, command: str) -> str:
    """docs/reliability.md from the measurements."""
    import datetime as dt

    kb = summarize(res["kill_to_brake_s"])
    kt = summarize(res["kill_to_brake_timeout_only_s"])
    est = res["estop"]
    el = summarize(est["latency_s"])
    lid = res["lidar"]
    rp, gr = summarize(lid["replug_s"]), summarize(lid["garbage_reset_s"])
    gv, hv = summarize(lid.get("garbage_recover_s", [])), summarize(lid.get("health_recover_s", []))
    soak = res["soak"]
    rows = [
        ["controller kill -9 -> brake at the VESC (liveliness)", f"{kb['n']} kills",
         f"median {_ms(kb)} ms, max {_ms(kb, 'max')} ms", "median <= 50 ms"],
        ["same, timeout only (follow_liveliness = false, timeout_s 0.25)", f"{kt['n']} kills",
         f"median {_ms(kt)} ms, max {_ms(kt, 'max')} ms", "(reference)"],
        ["spurious brakes, live controller at 10 Hz", f"{soak.get('seconds', 0)} s",
         f"{soak.get('brake_episodes', 'n/a')} episodes ({soak.get('brake_frames', 'n/a')} brake frames); "
         f"command gaps p99 {soak.get('cmd_gap_p99_ms', 'n/a')} ms, max {soak.get('cmd_gap_max_ms', 'n/a')} ms, "
         f"{soak.get('cmd_gaps_over_timeout', 'n/a')} over the {soak.get('timeout_s', 'n/a')} s timeout; "
         f"load average {soak.get('load_avg_5min', 'n/a')} on {os.cpu_count()} cores", "0"],
        ["e-stop put -> brake", f"{el['n']} e-stops", f"median {_ms(el)} ms, max {_ms(el, 'max')} ms", ""],
        ["e-stop latched across actuator kill -9 + restart", "", str(est.get("latched_after_restart")), "True"],
        ["\" clear\\n\" does not clear; exactly \"clear\" does", "",
         f"{est.get('near_clear_ignored')} / {est.get('clear_drives')}", "True / True"],
        ["e-stop published while the actuator is down holds at start", "", str(est.get("estop_while_down_holds")),
         "True"],
        ["lidar replug -> first scan (shipped timings)", f"{rp['n']} replugs",
         f"median {_ms(rp)} ms, max {_ms(rp, 'max')} ms", "<= 1 s"],
        [f"lidar garbage-only stream -> reset (data_timeout_s {lid['data_timeout_s']})", f"{gr['n']} runs",
         f"median {_ms(gr)} ms, max {_ms(gr, 'max')} ms", "the data timeout (+ one read)"],
        ["lidar garbage ends (at the reset) -> first scan (emulator: 0.1 s boot)", f"{gv['n']} runs",
         f"median {_ms(gv)} ms, max {_ms(gv, 'max')} ms", "<= 1.5 s"],
        [f"lidar 0.5 s health error ends -> first scan (silence_timeout_s {lid.get('silence_timeout_s')})",
         f"{hv['n']} runs", f"median {_ms(hv)} ms, max {_ms(hv, 'max')} ms", "<= 1.5 s"],
    ]
    for outage, delays in res["router_restart_s"].items():
        s = summarize(delays)
        rows.append([f"router SIGKILL, {outage} s outage, restart -> commands flow", f"{s['n']} restarts",
                     f"median {_ms(s)} ms, max {_ms(s, 'max')} ms", "<= 1 s after listening"])
    fz = res.get("fuzz") or {}
    fuzz_md = "(not run)"
    if fz:
        frows = [[n, "yes" if r["alive"] else "**no**", r["sent"], r["received"], r["expected_invalid"], r["invalid"],
                  r["errors"], f"{r['rss_before_mb']} -> {r['rss_mid_mb']} -> {r['rss_after_mb']}"]
                 for n, r in fz["services"].items()]
        fuzz_md = (f"{fz['per_key']:,} payloads on each of the {fz['keys']} input keys (the racecav keys and "
                   f"`racecav ros2`'s ROS 2 /drive, AckermannDriveStamped CDR up to 4x ros2.max_payload_bytes) "
                   f"({sum(fz['sent_by_key'].values()):,} in {fz['seconds']} s, after a warm-up), "
                   f"{sum(fz['invalid_by_key'].values()):,} of them invalid by the codec's own judgement:\n\n"
                   + table(frows, ["service", "alive", "sent to its keys", "received", "invalid expected",
                                   "invalid counted", "errors", "RSS MB: before -> half -> end"]))
    stamp = dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return f"""# Reliability

Written by `{command}` on {stamp}, {machine()}. Nothing here is typed by hand: rerun the command
to regenerate it. Real processes throughout (router, actuator, controllers, sim, policy,
baseline, safety; the VESC and RPLIDAR emulators on ptys).

## Figures

{table(rows, ["what", "n", "measured", "target"])}

## Fuzz: no input kills or silences a service

{fuzz_md}

"received" counts every payload a service got on any of its keys (its own traffic included, so
it can exceed what was sent); "invalid counted" must be at least what the codec rejects;
"errors" counts exceptions caught in callbacks, queries and the loop (0: every bad input was
refused by validation, none reached code that raised). RSS is read after a warm-up of 300
payloads per key, after half of the payloads and at the end: a leak per payload grows the
second half as much as the first; allocator and queue high-water marks grow once.

## How it works

**No input kills a service.** `racecav.common.codec.decode` raises only `DecodeError`:
strict types (no strings or booleans coerced into numbers), integers within int64, finite angles
within two turns, a scan increment of at least 1e-5 rad and at most 16,384 rays, DriveCommands
whose `throttle` equals `clip(a_throttle, 0, 1)` and whose steering fields agree in sign. Query
payloads (sim reset/scenario: seeds in [0, 2^32-1], known scenario names) are checked and
refused with an error reply. Any exception escaping a subscriber callback, a query handler or a
service's `step()` is caught by the Service base, counted (`errors`, `last_error` in the
status), logged rate-limited (the first of a kind with its traceback), and the service goes on.

**E-stop that survives.** Two copies of the latch: the actuator writes
`<actuator.state_dir>/estop-<car>.json` (atomic, fsynced; systemd's StateDirectory,
/var/lib/racecav) on every change, and `racecav router` keeps the latest state and answers
`racecav/<car>/router/estop`. The actuator starts latched if either copy says so, so a kill -9
and restart, and an e-stop sent while the actuator was down, both leave the car stopped until
exactly `clear` (not `CLEAR`, not ` clear\\n`) arrives. The copies are ORed: a clear seen by
only one of them needs repeating (a spurious stop costs a clear; a lost stop costs a crash).

**Fail-safe in milliseconds.** The actuator follows the liveliness token of the controller it
obeys (`racecav/<car>/<actuator.controller>/alive`). A dead process loses its TCP link, the router
withdraws the token, and the actuator drops the controller's command at once (`mux.lost`), so
the next frame is the brake. `actuator.timeout_s` (0.25 s, 2.5 periods of the 10 Hz control
rate) stays the backstop for a controller that is alive but silent. The simulator applies the
same rule to the controller whose command is in force.

**Lidar recovery.** A re-opened port (a replug) skips the RESET (the device has just powered
up): STOP, 50 ms, flush, handshake; if that fails, the next attempt resets. The port is polled
every `sensor.reconnect_s` = 0.1 s. A stream that keeps sending bytes of which nothing decodes
counts as no data: the device is reset after `sensor.data_timeout_s`. A device that goes silent
(a health error stops its scan) is asked its health and reset after `sensor.silence_timeout_s`
(0.3 s). After RESET the driver waits `sensor.reset_wait_s` = 2 ms, what Slamtec's "RPLIDAR
Interface Protocol and Application Notes" documents ("Core Reset (RESET) Request", Fig. 4-3: wait
at least 2 ms before sending another request), then sends GET_INFO every `sensor.reset_poll_s`
(50 ms) until the rebooted core answers (at most `sensor.reset_timeout_s`, 2 s), instead of a
fixed 2 s. The times above are on the emulator, which boots in 0.1 s; a real S2 adds its own
boot time (about 2 s) to the recovery after a reset, not to a replug.

**ROS 2 input.** The mirror's `/drive` refuses a payload over `ros2.max_payload_bytes` (1024)
before parsing it and counts it as invalid, like CDR its converter rejects.

**Router restart.** Clients retry the router every `bus.reconnect_initial_s` (0.1 s) growing
1.5x up to `bus.reconnect_max_s` (0.25 s) instead of zenoh's 1 s to 4 s.

**Processes.** Every process a command starts (benches, eval, demo) is registered in
`racecav.common.procs`; SIGTERM/SIGHUP raise SystemExit like SIGINT raises KeyboardInterrupt,
and everything still running is stopped at exit. Bad set-ups (a config that is a directory or
not UTF-8, an invalid or unreachable `bus.connect`, a router endpoint in use or invalid, a
missing router config file, an emulator link in a missing directory) exit 2 with one line naming
the file, endpoint or port. So does every invalid configuration field, from a file or a
`RACECAV_*` variable, and every invalid option, naming the option and the field it sets and the
rule: `racecav baseline: --v-ref (baseline.v_ref): Input should be greater than or equal to 0
(got -1.0)`.

## Tests

Real processes, a real router, the emulators on ptys (part of `make test`):

```sh
nice -n 10 .venv/bin/pytest tests/test_bus_codec.py tests/test_hardening_*.py tests/test_cli_setup.py -q
```

- test_bus_codec: every reported killer payload (stamps beyond int64, +-1e308 angles, a 5e-324
  increment, maps for arrays, strings and booleans for numbers, contradicting DriveCommands)
  is a DecodeError; hypothesis over every field;
- test_hardening_fuzz: hypothesis payloads on every input key and bad payloads on every sim
  query through a real router with actuator, policy, baseline, safety, sim, the ROS 2 mirror
  (incl. hostile /drive CDR with and without the rmw_zenoh attachment), the recorder (bad
  `rotate` queries refused; its run files read back complete, every payload in them) and the
  Foxglove view running: alive, counted, `errors` 0, RSS flat, every service still answers
  valid input;
- test_hardening_failsafe: e-stop across kill -9 and restart, exact `clear`, e-stop while the
  actuator is down, kill -9 of the controller -> brake (median <= 50 ms over 3 kills), the
  simulator's same rule, a missing serial port in `last_error`, sim-scan answers refused;
- test_hardening_sensor: replug -> first scan with the shipped timings, garbage-only -> reset,
  scans within 1.5 s of the end of garbage and of a health error;
- test_hardening_access: every account against the access table of docs/deploy.md;
- test_cli_setup: every configuration field (through the environment and a TOML file), every
  typed option of every command, every option that sets a configuration field, bad paths and
  devices: exit 2 and one line naming the field, option or path (found by walking the
  configuration model and the argument parsers, in-process);
- test_hardening_procs: bad set-ups exit 2 with one line, benches and the demo killed mid-run
  (SIGTERM, SIGINT) leave no process, a failing command stops its router, the emulator's
  SIGTERM removes its link, commands flow within 1 s of a router restart.
"""
