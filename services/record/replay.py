"""``racecav replay run.mcap``: feed a recorded run's scans to a running controller and report how
its commands differ from the recorded ones (a regression check of a new policy on a recorded
drive).

The scans are the recorded bus payloads, republished on racecav/<car>/scan:
- ``--rate R``: at their recorded pace (scan stamps), R times faster;
- ``--lockstep``: one scan, wait for the command answering it, then the next (deterministic:
  no scan is dropped or answered late, so the same weights give the same commands); a scan not
  answered within 0.5 s is sent again until ``--timeout``.
Scans recorded from the real sensor (source "real", stamped with that host's monotonic clock) are
re-stamped with this host's clock as they are sent, or the controller would find them stale;
answers are matched to scans by seq and stamp either way. Each new command is compared with the
recorded command that answered the same scan: normalised actions (a_T, a_delta) and steering.
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from racecav.common import keys
from racecav.common.codec import DecodeError, decode
from racecav.common.config import Config
from racecav.common.messages import DriveCommand, Scan

EXAMPLES = """examples:
  racecav record --keys scan cmd -o run.mcap       # record a drive
  racecav policy --model new.npz &                 # the controller to check
  racecav replay run.mcap --lockstep               # every scan, answer by answer
  racecav replay run.mcap --rate 2 --json diff.json
  racecav replay run.mcap --lockstep --tolerance 1e-6   # exit 1 on any difference
  racecav replay run.mcap --no-replay --plot run.png --world intersection   # just draw it
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", help="run file written by racecav record")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--rate", type=float, default=1.0, help="publish at the recorded pace times R (default 1)")
    g.add_argument("--lockstep", action="store_true", help="wait for each scan's command before the next")
    p.add_argument("--controller", help="service to wait for (default: whichever of policy, baseline is alive)")
    p.add_argument("--source-car", help="car whose scans to replay (default: the file's only car)")
    p.add_argument("--timeout", type=float, default=2.0, help="lockstep: seconds to wait for each answer")
    p.add_argument("--limit", type=int, help="replay at most this many scans")
    p.add_argument("--tolerance", type=float,
                   help="exit 1 if a normalised action differs by more than this, or a scan gets no answer")
    p.add_argument("--json", help="write the report to this file")
    p.add_argument("--plot", metavar="PNG", help="draw the run (paths, scans, recorded and replayed commands)")
    p.add_argument("--world", help="--plot: draw this world's walls under the paths")
    p.add_argument("--no-replay", action="store_true", help="only read the file (with --plot: just draw it)")
    p.epilog = EXAMPLES
    p.formatter_class = argparse.RawDescriptionHelpFormatter


def load_run(path: str | Path, car: str | None = None) -> tuple[str, list[Scan], dict[tuple[int, int], DriveCommand]]:
    """(car, scans in order without repeats, recorded command per (scan seq, scan stamp)).

    :raises RunFileError: for a missing or unreadable file, or one without scans, naming it.
    """
    from racecav.services.record.mcapfile import RunFileError, read_raw, run_cars

    samples = read_raw(path)
    cars = run_cars(samples)
    if car is None:
        if len(cars) != 1:
            raise RunFileError(f"{path}: scans of {len(cars)} cars ({', '.join(cars) or 'none'}): "
                               "pick one with --source-car")
        car = cars[0]
    elif car not in cars:
        raise RunFileError(f"{path}: no scans of car {car!r} (cars: {', '.join(cars) or 'none'})")
    scan_key, cmd_key = keys.topic(car, keys.SCAN), keys.topic(car, keys.CMD)
    scans: list[Scan] = []
    seen: set[tuple[int, int]] = set()
    recorded: dict[tuple[int, int], DriveCommand] = {}
    for s in samples:
        try:
            if s.key == scan_key:
                scan = decode(s.payload, Scan)
                if (scan.seq, scan.stamp_ns) not in seen:  # lockstep republishes an unanswered scan
                    seen.add((scan.seq, scan.stamp_ns))
                    scans.append(scan)
            elif s.key == cmd_key:
                cmd = decode(s.payload, DriveCommand)
                recorded.setdefault((cmd.scan_seq, cmd.scan_stamp_ns), cmd)
        except DecodeError:
            continue  # recorded as received; an invalid sample is not replayed
    return car, scans, recorded


class Answers:
    """Commands on racecav/<car>/cmd, by the (seq, stamp) of the scan they answer."""

    def __init__(self, session, car: str):
        self._cond = threading.Condition()
        self.by_scan: dict[tuple[int, int], DriveCommand] = {}
        self.invalid = 0
        self._sub = session.declare_subscriber(keys.topic(car, keys.CMD), self._on)

    def _on(self, sample) -> None:
        try:
            cmd = decode(sample.payload.to_bytes(), DriveCommand)
        except DecodeError:
            self.invalid += 1
            return
        with self._cond:
            self.by_scan.setdefault((cmd.scan_seq, cmd.scan_stamp_ns), cmd)
            self._cond.notify_all()

    def wait(self, key: tuple[int, int], timeout: float) -> DriveCommand | None:
        with self._cond:
            self._cond.wait_for(lambda: key in self.by_scan, timeout)
            return self.by_scan.get(key)

    def close(self) -> None:
        self._sub.undeclare()


def replay(session, car: str, scans: list[Scan], lockstep: bool, rate: float = 1.0,
           timeout: float = 2.0) -> dict[tuple[int, int], DriveCommand | None]:
    """Publish ``scans`` on racecav/<car>/scan; the answer to each, by the scan's original
    (seq, stamp) (None: no answer)."""
    from tqdm import tqdm

    from racecav.common.codec import encode

    answers = Answers(session, car)
    pub = session.declare_publisher(keys.topic(car, keys.SCAN))
    sent: list[tuple[tuple[int, int], list[tuple[int, int]]]] = []  # (original, as sent each time)

    def send(scan: Scan) -> tuple[int, int]:
        out = scan
        if scan.source == "real":  # the controller judges real stamps against its own clock
            out = scan.model_copy(update={"stamp_ns": time.monotonic_ns()})
        pub.put(encode(out))
        return out.seq, out.stamp_ns

    try:
        t0_wall, t0_stamp = time.monotonic(), scans[0].stamp_ns if scans else 0
        for scan in tqdm(scans, desc="replay", unit="scan", disable=None):
            if not lockstep and rate > 0:
                delay = t0_wall + (scan.stamp_ns - t0_stamp) / 1e9 / rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            key = send(scan)
            sent.append(((scan.seq, scan.stamp_ns), [key]))
            if lockstep:
                # like the sim's lockstep: a scan not answered within 0.5 s is sent again (a
                # controller that had not subscribed yet), until the timeout
                deadline = time.monotonic() + timeout
                while answers.wait(key, min(0.5, max(deadline - time.monotonic(), 0.0))) is None:
                    if time.monotonic() >= deadline:
                        break
                    key = send(scan)
                    sent[-1][1].append(key)
        if not lockstep and sent:  # the last answers are still on their way
            answers.wait(sent[-1][1][0], min(timeout, 1.0))
        out: dict[tuple[int, int], DriveCommand | None] = {}
        for orig, keys_sent in sent:
            out[orig] = next((answers.by_scan[k] for k in keys_sent if k in answers.by_scan), None)
        return out
    finally:
        pub.undeclare()
        answers.close()


def compare(recorded: dict[tuple[int, int], DriveCommand],
            new: dict[tuple[int, int], DriveCommand | None]) -> dict[str, Any]:
    """How the new commands differ from the recorded ones, scan by scan."""
    pairs = [(recorded[k], c) for k, c in new.items() if c is not None and k in recorded]
    rep: dict[str, Any] = {
        "scans": len(new), "answered": sum(c is not None for c in new.values()),
        "recorded_answers": sum(k in recorded for k in new), "compared": len(pairs),
        "identical": sum(a.a_throttle == b.a_throttle and a.a_steer == b.a_steer for a, b in pairs),
        "sources": sorted({c.source for c in new.values() if c is not None}),
        "recorded_sources": sorted({c.source for c in recorded.values()}),
    }
    for field in ("a_throttle", "a_steer", "steering_angle", "throttle"):
        d = np.array([abs(getattr(b, field) - getattr(a, field)) for a, b in pairs], dtype=np.float64)
        rep[f"{field}_max_abs_diff"] = float(d.max()) if d.size else 0.0
        rep[f"{field}_mean_abs_diff"] = float(d.mean()) if d.size else 0.0
    return rep


def format_report(rep: dict[str, Any]) -> str:
    lines = [f"scans replayed: {rep['scans']}, answered: {rep['answered']} "
             f"({', '.join(rep['sources']) or 'no controller'}); recorded answers: {rep['recorded_answers']} "
             f"({', '.join(rep['recorded_sources']) or 'none'})",
             f"identical commands: {rep['identical']} of {rep['compared']} compared"]
    for field in ("a_throttle", "a_steer", "steering_angle"):
        lines.append(f"  {field:15s} max |diff| {rep[f'{field}_max_abs_diff']:.3g}  "
                     f"mean |diff| {rep[f'{field}_mean_abs_diff']:.3g}")
    return "\n".join(lines)


def _wait_controller(session, car: str, name: str | None, timeout: float = 30.0) -> str:
    from racecav.common.client import live_services

    wanted = [name] if name else ["policy", "baseline"]
    deadline = time.monotonic() + timeout
    while True:
        live = live_services(session, car, timeout=0.5)
        for n in wanted:
            if n in live:
                return n
        if time.monotonic() > deadline:
            raise TimeoutError(f"no {' or '.join(wanted)} alive on car {car} (live: {', '.join(live) or 'none'})")
        time.sleep(0.2)


def run(args: argparse.Namespace, cfg: Config) -> int:
    from racecav.common.client import open_session
    from racecav.services.record.mcapfile import RunFileError

    try:
        _src, scans, recorded = load_run(args.file, args.source_car)
    except (RunFileError, ImportError) as e:
        print(f"racecav replay: {e}")
        return 2
    if args.limit:
        scans = scans[:args.limit]
    if not scans:
        print(f"racecav replay: {args.file}: no valid scans to replay")
        return 2
    if args.no_replay:
        print(f"{args.file}: {len(scans)} scans, {len(recorded)} recorded commands")
        if args.plot:
            from racecav.services.record.plot import plot_run

            print(f"plot: {plot_run(args.file, args.plot, _src, args.world)}")
        return 0
    car = cfg.bus.car
    with open_session(cfg) as session:
        try:
            ctl = _wait_controller(session, car, args.controller)
        except TimeoutError as e:
            print(f"racecav replay: {e}")
            return 2
        print(f"replaying {len(scans)} scans of {args.file} into {ctl} on car {car} "
              f"({'lockstep' if args.lockstep else f'rate {args.rate:g}'})")
        new = replay(session, car, scans, args.lockstep, args.rate, args.timeout)
    rep = compare(recorded, new)
    rep.update(file=str(args.file), controller=ctl, mode="lockstep" if args.lockstep else f"rate {args.rate:g}")
    print(format_report(rep))
    if args.json:
        Path(args.json).write_text(json.dumps(rep, indent=2))
    if args.plot:
        from racecav.services.record.plot import plot_run

        print(f"plot: {plot_run(args.file, args.plot, _src, args.world, new_cmds=new)}")
    if args.tolerance is not None:
        worst = max(rep["a_throttle_max_abs_diff"], rep["a_steer_max_abs_diff"])
        if worst > args.tolerance or rep["answered"] < rep["scans"]:
            return 1
    return 0
