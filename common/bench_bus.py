"""``racecav bench bus``: what the bus costs a control loop.

Three processes, as on the car: a router, a publisher service sending a 170-ray Scan at 60 Hz
(stamped with the system-wide monotonic clock just before ``put``), and this process receiving
it as a service would (decode + validate in the callback). One-way latency = arrival - stamp.
Then status-query latency against the publisher service; all of it once with both ends clients
of the router (the default) and once in peer mode (direct link); and the codec alone in-process.
Targets (issue 2): one-way median <= 0.3 ms, p99 <= 1 ms; codec encode+decode <= 20 us median.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time

import numpy as np

from racecav.common import keys
from racecav.common.bench import dump_json, summarize, table, write_section
from racecav.common.config import Config
from racecav.common.messages import Scan

N_RAYS = 170


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--samples", type=int, default=1200, help="scans to time (at --rate)")
    p.add_argument("--rate", type=float, default=60.0, help="scan rate (Hz)")
    p.add_argument("--queries", type=int, default=200, help="status queries to time")


def sample_scan(seq: int = 0, stamp_ns: int = 0) -> Scan:
    """A realistic 170-ray frontal scan (the policy's observation layout)."""
    rng = np.random.default_rng(seq)
    return Scan(stamp_ns=stamp_ns, seq=seq, source="sim", angle_min=-np.pi / 4, angle_max=np.pi / 4,
                angle_increment=(np.pi / 2) / (N_RAYS - 1), scan_time=1 / 60, range_min=0.05, range_max=12.0,
                ranges=rng.uniform(0.3, 12.0, N_RAYS).astype(np.float32))


def bench_codec(n: int = 5000) -> dict:
    from racecav.common.codec import decode, encode

    msg = sample_scan(1, 1)
    for _ in range(200):
        decode(encode(msg), Scan)
    t = np.empty(n)
    for i in range(n):
        t0 = time.perf_counter_ns()
        decode(encode(msg), Scan)
        t[i] = time.perf_counter_ns() - t0
    return summarize(t, 1e-3)  # us


def publisher_main(rate: float, count: int) -> int:
    """The publisher process: a Service that publishes ``count`` scans at ``rate`` Hz."""
    from racecav.common.bus import Service
    from racecav.common.config import load_config

    svc = Service(load_config(), "benchpub")
    svc.open()
    try:
        pub = svc.publisher(svc.topic(keys.SCAN))
        time.sleep(1.0)  # let the subscriber's interest reach us through the router
        period = 1.0 / rate
        base = sample_scan(0)
        next_t = time.monotonic()
        for seq in range(count):
            next_t += period
            time.sleep(max(0.0, next_t - time.monotonic()))
            base.seq, base.stamp_ns = seq, time.monotonic_ns()
            pub.put(base)
        svc.stop_event.wait(3600)  # keep answering status queries until told to stop
    finally:
        svc.close()
    return 0


def _measure(cfg: Config, endpoint: str, mode: str, args, warmup: int) -> tuple[list[int], list[int]]:
    """One publisher process and this process, both in bus ``mode``: one-way scan latencies
    and status-query round trips (ns)."""
    import zenoh

    from racecav.common import procs
    from racecav.common.client import get_status, open_session
    from racecav.common.codec import decode

    lat: list[int] = []
    q: list[int] = []
    done = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        msg = decode(sample.payload.to_bytes(), Scan)
        now = time.monotonic_ns()
        if msg.seq >= warmup:
            lat.append(now - msg.stamp_ns)
        if msg.seq == warmup + args.samples - 1:
            done.set()

    env = procs.bus_env(endpoint, extra={"RACECAV_BUS__MODE": mode})
    bus = cfg.bus.model_copy(update={"connect": [endpoint], "mode": mode})
    with open_session(cfg.model_copy(update={"bus": bus})) as session:
        sub = session.declare_subscriber(keys.topic(bus.car, keys.SCAN), on_sample)
        pub_proc = procs.track(subprocess.Popen([sys.executable, "-m", "racecav.common.bench_bus", "--publisher",
                                                  str(args.rate), str(warmup + args.samples)], env=env,
                                                 start_new_session=True))
        try:
            procs.wait_alive(session, bus.car, "benchpub", proc=pub_proc)
            total_s = (warmup + args.samples) / args.rate + 10
            if not done.wait(total_s):
                print(f"warning ({mode}): received {len(lat)} of {args.samples} timed scans", file=sys.stderr)
            for _ in range(args.queries):
                t0 = time.perf_counter_ns()
                get_status(session, bus.car, "benchpub")
                q.append(time.perf_counter_ns() - t0)
                time.sleep(0.01)
        finally:
            sub.undeclare()
            procs.stop(pub_proc)
    return lat, q


def run(args: argparse.Namespace, cfg: Config) -> int:
    from racecav.common import procs

    codec = bench_codec()
    warmup = 60
    with procs.router() as endpoint:
        lat, q = _measure(cfg, endpoint, "client", args, warmup)
        lat_peer, q_peer = _measure(cfg, endpoint, "peer", args, warmup)

    one_way, one_way_peer = summarize(lat, 1e-3), summarize(lat_peer, 1e-3)
    query, query_peer = summarize(q, 1e-3), summarize(q_peer, 1e-3)
    lost, lost_peer = args.samples - len(lat), args.samples - len(lat_peer)
    results = {"one_way_us": one_way, "status_query_us": query, "codec_us": codec,
               "peer": {"one_way_us": one_way_peer, "status_query_us": query_peer, "scans_lost": lost_peer},
               "scans_sent": args.samples, "scans_lost": lost, "rate_hz": args.rate,
               "targets": {"one_way_median_us": 300, "one_way_p99_us": 1000, "codec_median_us": 20}}

    def row(what, d, target=""):
        return [what, f"{d['median']:.0f}", f"{d['p99']:.0f}", target]

    rows = [row("scan one-way, pub -> router -> sub (170 rays, %g Hz; client mode, the default)" % args.rate,
                one_way, "<= 300 / <= 1000"),
            row("scan one-way, pub -> sub over a direct link (peer mode)", one_way_peer, "<= 300 / <= 1000"),
            row("status query round trip (client mode, through the router)", query),
            row("status query round trip (peer mode)", query_peer),
            ["codec encode + decode of a Scan (in-process)", f"{codec['median']:.1f}", f"{codec['p99']:.1f}", "<= 20 median"]]
    md = table(rows, ["what", "median (us)", "p99 (us)", "target (us)"])
    load = os.getloadavg()[0]
    md += (f"\n\n{args.samples} scans timed after {warmup} warm-up per mode, {lost} lost (client), {lost_peer} "
           f"lost (peer); {args.queries} status queries "
           f"at 100 Hz. 1-minute load average {load:.1f} on {os.cpu_count()} cores at the end of the run.")
    results["load_average"] = load
    print(md)
    dump_json(args.json, results)
    if not args.no_doc:
        write_section("bus", "racecav bench bus", md)
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--publisher":
        sys.exit(publisher_main(float(sys.argv[2]), int(sys.argv[3])))
    sys.exit("usage: python -m racecav.common.bench_bus --publisher RATE COUNT")
