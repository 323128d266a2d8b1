"""`racecav bench lidar`: RPLIDAR decoding and preprocessing cost, and the driver's CPU share at 10 Hz.

1. decode: ScanStream on DenseBoost bytes (80 capsules = one revolution at 10 Hz) fed in 4 KB reads;
2. preprocess: one revolution (3,200 samples) to the Scan message (170 rays);
3. live: `racecav emulate rplidar` in a subprocess, the real driver in this process for a few
   seconds: revolutions/s received and this process's CPU time per second (driver + decoding).
"""

from __future__ import annotations

import argparse
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--revs", type=int, default=300, help="revolutions for the offline measurements")
    p.add_argument("--live-s", type=float, default=5.0, help="seconds of live driver measurement")


def _dense_revolutions(n_revs: int) -> tuple[list[bytes], object]:
    from racecav.services.sensor import rplidar_protocol as rp
    from racecav.services.sensor.emulator import WallScene, default_walls

    scene = WallScene(default_walls())
    spr = 3200
    out = []
    for k in range(80 * n_revs):
        q0 = round((k * 40 % spr) * 360 * 64 / spr) % (360 * 64)
        a = q0 / 64 + 4.5 * np.arange(40) / 40
        out.append(rp.encode_dense_capsule(q0 / 64, scene.ranges_mm(np.mod(a, 360.0)), new_scan=(k == 0)))
    return out, scene


def run(args: argparse.Namespace, cfg) -> int:
    from racecav.common import procs
    from racecav.common.bench import dump_json, summarize, table, write_section
    from racecav.common.lidar import LidarSpec
    from racecav.services.sensor import rplidar_protocol as rp
    from racecav.services.sensor.preprocess import cut_angle_deg, revolution_to_scan
    from racecav.services.sensor.rplidar_driver import RplidarDriver

    spec = LidarSpec()
    caps, _scene = _dense_revolutions(min(args.revs, 50))
    data = b"".join(caps)
    decode_ms = []
    for _ in range(max(1, args.revs // 50)):
        s = rp.ScanStream(rp.ANS_DENSE)
        asm = rp.RevolutionAssembler(cut_angle_deg(spec))
        t0 = time.perf_counter()
        for i in range(0, len(data), 4096):
            asm.add(s.feed(data[i:i + 4096]))
        decode_ms.append((time.perf_counter() - t0) * 1e3 / (len(caps) / 80))
    revs = rp.RevolutionAssembler(cut_angle_deg(spec)).add(rp.ScanStream(rp.ANS_DENSE).feed(data))
    prep_us = []
    for k in range(args.revs):
        r = revs[k % len(revs)]
        t0 = time.perf_counter()
        revolution_to_scan(r.angle_deg, r.dist_mm, 10**9, 31.25, k, spec)
        prep_us.append((time.perf_counter() - t0) * 1e6)

    # Live: emulator in its own process, the driver here.
    with tempfile.TemporaryDirectory() as tmp:
        link = Path(tmp) / "rplidar"
        emu = procs.start(["emulate", "rplidar", "--link", str(link), "--reset-s", "0.1"], procs.bus_env("tcp/127.0.0.1:1"),
                          Path(tmp) / "emu.log")
        try:
            deadline = time.monotonic() + 20
            while not link.exists():
                if time.monotonic() > deadline or emu.poll() is not None:
                    raise RuntimeError("emulator did not start")
                time.sleep(0.05)
            got: list[float] = []
            drv = RplidarDriver(str(link), lambda r: got.append(time.monotonic()), reset_wait_s=0.2, spinup_s=0.05,
                                cut_deg=cut_angle_deg(spec))
            th = drv.start_thread()
            while len(got) < 2 and time.monotonic() < deadline:
                time.sleep(0.05)
            c0, t0, n0 = time.process_time(), time.monotonic(), len(got)
            time.sleep(args.live_s)
            cpu = (time.process_time() - c0) / (time.monotonic() - t0)
            rate = (len(got) - n0) / (time.monotonic() - t0)
            drv.stop_event.set()
            th.join(3)
        finally:
            procs.stop(emu)
    d, p = summarize(decode_ms), summarize(prep_us)
    results = {"decode_ms_per_rev": d, "preprocess_us_per_rev": p, "live_revs_per_s": rate,
               "live_cpu_fraction": cpu, "parser": drv.stats.parser.as_dict()}
    md = table([
        ["decode one DenseBoost revolution (80 capsules, 3,200 samples)", f"{d['median']:.2f} ms", f"{d['p99']:.2f} ms"],
        ["revolution -> 170-ray Scan (preprocess)", f"{p['median']:.0f} us", f"{p['p99']:.0f} us"],
    ], ["what", "median", "p99"])
    md += (f"\n\nLive over a pty against `racecav emulate rplidar` (paced like the 1 Mbaud link): "
           f"{rate:.1f} revolutions/s received, driver process CPU {cpu * 100:.1f} % of one core, "
           f"parser errors {drv.stats.parser.errors()}.\n")
    print(md)
    dump_json(args.json, results)
    if not args.no_doc:
        write_section("lidar", "racecav bench lidar", md)
    return 0
