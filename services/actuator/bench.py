"""`racecav bench vesc`: command latency to the VESC and watchdog reaction, measured at the emulator.

A real router and a real `racecav actuator` process; the VESC emulator runs in this process, so
its frame arrival times and this process's publish times share one monotonic clock.
1. latency: DriveCommand published -> its SET_RPM frame read by the emulator (each command
   carries a distinct throttle so its frame can be recognised);
2. watchdog: the controller stops; time from the last command's frame to the first neutral frame.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--trials", type=int, default=30, help="controller start/stop trials")


def run(args: argparse.Namespace, cfg) -> int:
    from racecav.common import keys, procs
    from racecav.common.bench import dump_json, summarize, table, write_section
    from racecav.common.client import open_session
    from racecav.common.codec import encode
    from racecav.common.config import load_config
    from racecav.common.messages import DriveCommand
    from racecav.common.vehicle import load_car
    from racecav.services.actuator.control import Mapping
    from racecav.services.actuator.emulator import VescEmulator

    car = "car0"
    lat_ms, gap_ms = [], []
    with tempfile.TemporaryDirectory() as tmp, procs.router(log_path=Path(tmp) / "router.log") as ep:
        emu = VescEmulator(link=Path(tmp) / "vesc").start()
        bus = load_config(environ={"RACECAV_BUS__CONNECT": f'["{ep}"]'})
        act = procs.start(["actuator", "--port", emu.path], procs.bus_env(ep, extra={"RACECAV_ACTUATOR__TIMEOUT_S": "0.1"}), Path(tmp) / "actuator.log")
        session = open_session(bus)
        try:
            procs.wait_alive(session, car, "actuator", proc=act)
            mapping = Mapping(bus.actuator, load_car(bus.actuator.car))
            pub = session.declare_publisher(keys.topic(car, keys.CMD), express=True)
            seq = 0
            for trial in range(args.trials):
                sent: dict[int, float] = {}
                for k in range(10):  # 10 commands at 50 Hz, each with its own throttle
                    throttle = 0.3 + 0.001 * (trial * 10 + k) % 0.6
                    erpm = round(mapping.erpm(throttle))
                    sent[erpm] = time.monotonic()
                    pub.put(encode(DriveCommand(stamp_ns=time.monotonic_ns(), seq=seq, source="policy",
                                                a_throttle=throttle, a_steer=0.0, throttle=throttle,
                                                steering_angle=0.0)))
                    seq += 1
                    time.sleep(0.02)
                last_erpm = erpm
                time.sleep(0.3)
                frames = emu.frames("SET_RPM", "SET_CURRENT_BRAKE")
                first: dict[float, float] = {}
                for r in frames:
                    if r.name == "SET_RPM" and r.value not in first:
                        first[r.value] = r.t
                lat_ms += [(first[e] - t) * 1e3 for e, t in sent.items() if e in first]
                t_last = first[last_erpm]
                stop = next(r.t for r in frames if r.name == "SET_CURRENT_BRAKE" and r.t > t_last)
                gap_ms.append((stop - t_last) * 1e3)
        finally:
            session.close()
            procs.stop(act)
            emu.stop()
    lat, gap = summarize(lat_ms), summarize(gap_ms)
    md = table([
        ["DriveCommand published -> SET_RPM read by the VESC", f"{lat['median']:.2f} ms", f"{lat['p99']:.2f} ms",
         f"{lat['max']:.2f} ms", lat["n"]],
        ["last command at the VESC -> neutral frame (timeout 100 ms)", f"{gap['median']:.1f} ms", f"{gap['p99']:.1f} ms",
         f"{gap['max']:.1f} ms", gap["n"]],
    ], ["what", "median", "p99", "max", "n"])
    md += "\n\nThrough a real router and a real `racecav actuator`; frames timed by the VESC emulator on a pty.\n"
    print(md)
    dump_json(args.json, {"latency_ms": lat, "watchdog_gap_ms": gap})
    if not args.no_doc:
        write_section("vesc", "racecav bench vesc", md)
    return 0
