"""`racecav emulate record-scans`: save Scans from the bus (e.g. the simulator's) for the emulator to replay.

    racecav emulate record-scans --count 100 --out scans.npz     # while `racecav sim` runs
    racecav emulate rplidar --replay scans.npz                   # then, without the simulator

The file holds ``ranges`` (N, n_rays) float32 metres (+inf = no return), ``angle_min`` and
``angle_increment`` (rad, CCW, laser frame): what :class:`ReplayScene` reads.
"""

from __future__ import annotations

import argparse
import threading

import numpy as np


def save_replay(path, scans) -> None:
    """Write Scans (same geometry) as a replay file."""
    if not scans:
        raise ValueError("no scans to save")
    first = scans[0]
    for s in scans:
        if s.ranges.shape != first.ranges.shape or s.angle_min != first.angle_min:
            raise ValueError(f"scan seq {s.seq}: geometry differs from the first scan's")
    np.savez(path, ranges=np.stack([s.ranges for s in scans]).astype(np.float32),
             angle_min=np.float64(first.angle_min), angle_increment=np.float64(first.angle_increment))


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--count", type=int, default=100, help="scans to record")
    p.add_argument("--out", required=True, help=".npz file to write")
    p.add_argument("--timeout", type=float, default=60.0, help="give up after this many seconds")


def run(args: argparse.Namespace, cfg) -> int:
    from racecav.common import keys
    from racecav.common.client import open_session
    from racecav.common.codec import DecodeError, decode
    from racecav.common.messages import Scan

    scans: list[Scan] = []
    done = threading.Event()

    def on_sample(sample) -> None:
        try:
            scan = decode(sample.payload.to_bytes(), Scan)
        except DecodeError:
            return
        if len(scans) < args.count:
            scans.append(scan)
        if len(scans) >= args.count:
            done.set()

    with open_session(cfg) as session:
        sub = session.declare_subscriber(keys.topic(cfg.bus.car, keys.SCAN), on_sample)
        done.wait(args.timeout)
        sub.undeclare()
    if not scans:
        print("racecav emulate record-scans: no scan received")
        return 1
    save_replay(args.out, scans)
    print(f"{len(scans)} scans -> {args.out}")
    return 0
