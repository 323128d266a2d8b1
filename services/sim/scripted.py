"""``racecav scripted``: a controller that answers every scan with a scripted command.

For tests, demos and benchmarks of the simulator and the actuator: it behaves like the policy
service on the bus (newest scan in, one DriveCommand per scan out, naming the scan it answers)
but its commands come from a program instead of a network.

Program: ``"T,STEER,N;T,STEER,N;..."``: normalised throttle a_T and steering a_delta for N scans
each; after the last entry it keeps the last command (``--then hold``) or goes silent
(``--then stop``, so the car's watchdog brakes it).
"""

from __future__ import annotations

import argparse
import time

from racecav.common import keys
from racecav.common.bus import Service
from racecav.common.config import Config
from racecav.common.messages import DriveCommand, Scan
from racecav.common.vehicle import load_car, steer_from_action, throttle_from_action


def parse_program(text: str) -> list[tuple[float, float, int]]:
    """Parse "T,STEER,N;..." into [(a_T, a_delta, n_scans)].

    :raises ValueError: naming the entry that is malformed.
    """
    out = []
    for i, part in enumerate(p for p in text.split(";") if p.strip()):
        try:
            t, s, n = (x.strip() for x in part.split(","))
            entry = (float(t), float(s), int(n))
        except ValueError:
            raise ValueError(f"program entry {i} {part!r}: expected T,STEER,N") from None
        if not (-1 <= entry[0] <= 1 and -1 <= entry[1] <= 1 and entry[2] > 0):
            raise ValueError(f"program entry {i} {part!r}: T and STEER in [-1, 1], N > 0")
        out.append(entry)
    if not out:
        raise ValueError("program: empty")
    return out


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--program", default="0.5,0.0,1000", help='"T,STEER,N;..." (normalised actions, N scans each)')
    p.add_argument("--then", choices=["hold", "stop"], default="hold", help="after the program")
    p.add_argument("--compute-ms", type=float, default=None,
                   help="report this compute latency (default: the measured time to answer)")
    p.add_argument("--sleep-ms", type=float, default=0.0, help="pretend to compute for this long per scan")
    p.add_argument("--source", default="scripted", help="source field of the commands")
    p.add_argument("--car", default="slash", help="car file for the physical steering angle")


class ScriptedController(Service):
    def __init__(self, cfg: Config, program, then: str = "hold", compute_ms: float | None = None,
                 sleep_ms: float = 0.0, source: str = "scripted", car: str = "slash"):
        super().__init__(cfg, "scripted")
        self.program, self.then, self.compute_ms, self.sleep_ms = program, then, compute_ms, sleep_ms
        self.source, self.car_params = source, load_car(car)
        self.answered = 0
        self._last_seq = -1

    def setup(self) -> None:
        self.scans = self.inbox(self.topic(keys.SCAN), Scan)
        self.pub = self.publisher(self.topic(keys.CMD), command=True)

    def _action(self) -> tuple[float, float] | None:
        k = self.answered
        for a_t, a_s, n in self.program:
            if k < n:
                return a_t, a_s
            k -= n
        return self.program[-1][:2] if self.then == "hold" else None

    def step(self) -> None:
        scan = self.scans.take(timeout=0.2)
        if scan is None:
            return
        t0 = time.perf_counter_ns()
        repeat = scan.seq == self._last_seq  # a republished scan: answer it again, do not advance
        if repeat:
            self.answered -= 1
        action = self._action()
        if action is None:
            self.answered += repeat
            return
        if self.sleep_ms:
            time.sleep(self.sleep_ms / 1000)
        a_t, a_s = action
        compute_ns = int(self.compute_ms * 1e6) if self.compute_ms is not None else time.perf_counter_ns() - t0
        self.pub.put(DriveCommand(stamp_ns=scan.stamp_ns, seq=self.answered, source=self.source,
                                  a_throttle=a_t, a_steer=a_s, throttle=float(throttle_from_action(a_t)),
                                  steering_angle=float(steer_from_action(a_s, self.car_params)),
                                  scan_seq=scan.seq, scan_stamp_ns=scan.stamp_ns, compute_ns=compute_ns,
                                  scan_source=scan.source))
        self.answered += 1
        self._last_seq = scan.seq

    def info(self) -> dict:
        return {"answered": self.answered, "program_scans": sum(n for *_, n in self.program)}


def run(args: argparse.Namespace, cfg: Config) -> int:
    try:
        program = parse_program(args.program)
    except ValueError as e:
        print(f"racecav scripted: {e}")
        return 2
    return ScriptedController(cfg, program, args.then, args.compute_ms, args.sleep_ms, args.source,
                              args.car).run()
