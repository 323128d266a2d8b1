"""``racecav bench record``: does recording (or mirroring to ROS 2) slow the control path?

The policy's end-to-end latency (scan published -> its command received, through a local router,
as in ``racecav bench controllers``) is measured with nothing else on the bus, with a ``racecav
record`` process recording everything of the car, and with ``racecav ros2`` mirroring it; runs
alternate (off, record, ros2, off, record, ros2) so drift on the shared machine hits all alike.
Also: the CPU the recorder/mirror process spends, and their per-message cost in-process (ROS 2
CDR conversion, MCAP write).
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile
import time
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scans", type=int, default=400, help="scans per end-to-end run (default 400)")
    p.add_argument("--rate-hz", type=float, default=50.0, help="scan rate of the end-to-end runs")
    p.add_argument("--rounds", type=int, default=2, help="rounds of (off, record, ros2)")
    p.add_argument("--reps", type=int, default=2000, help="in-process repetitions per message type")


def _messages(n: int = 50):
    import numpy as np

    from racecav.common.messages import Scan, VehicleState

    rng = np.random.default_rng(0)
    out = []
    for i in range(n):
        r = rng.uniform(0.3, 12.0, 170).astype(np.float32)
        scan = Scan(stamp_ns=i, seq=i, source="sim", angle_min=-math.pi / 4, angle_max=math.pi / 4,
                    angle_increment=math.pi / 2 / 169, range_min=0.1, range_max=12.0, ranges=r)
        out.append((VehicleState(stamp_ns=i, seq=i, source="sim", x=0.1 * i, y=0.0, yaw=0.0, vx=1.0), scan))
    return out


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def in_process(reps: int, tmp: Path) -> dict:
    """Per-message cost (us) of the ROS 2 conversions and of writing a scan to a run file."""
    import numpy as np

    from racecav.common.bench import summarize
    from racecav.common.codec import encode
    from racecav.common.messages import DriveCommand
    from racecav.common.vehicle import load_car
    from racecav.services.record.mcapfile import RunWriter
    from racecav.services.ros2.msgs import Converter

    conv = Converter(load_car("slash"))
    state, scan = _messages(1)[0]
    cmd = DriveCommand(stamp_ns=1, source="policy", a_throttle=0.4, a_steer=0.1, throttle=0.4, steering_angle=0.03)
    res = {}
    for name, fn in (("LaserScan CDR", lambda: conv.scan(scan, 1)), ("Odometry CDR", lambda: conv.odometry(state, 1)),
                     ("AckermannDriveStamped CDR", lambda: conv.drive(cmd, 1))):
        t = []
        for _ in range(reps):
            t0 = time.perf_counter_ns()
            fn()
            t.append(time.perf_counter_ns() - t0)
        res[name] = summarize(np.array(t), 1e-3)
    w = RunWriter(tmp / "bench.mcap", "car0")
    payload = encode(scan)
    t = []
    for _ in range(reps):
        t0 = time.perf_counter_ns()
        w.write("racecav/car0/scan", payload)
        t.append(time.perf_counter_ns() - t0)
    w.close()
    res["record a scan (raw + LaserScan copy)"] = summarize(np.array(t), 1e-3)
    return res


def run(args: argparse.Namespace, cfg) -> int:
    import numpy as np

    from racecav.common import procs
    from racecav.common.bench import dump_json, summarize, table, write_section
    from racecav.services.bench_controllers import end_to_end

    tmp = Path(tempfile.mkdtemp(prefix="racecav-bench-record-"))
    msgs = _messages()
    lat: dict[str, list] = {"off": [], "record": [], "ros2": []}
    cpu: dict[str, list] = {"record": [], "ros2": []}
    lost = {k: 0 for k in lat}
    load0 = os.getloadavg()
    with procs.router(log_path=tmp / "router.log") as endpoint:
        from racecav.common.client import open_session
        from racecav.common.config import load_config

        with open_session(load_config(environ={"RACECAV_BUS__CONNECT": f'["{endpoint}"]'})) as s:
            for rnd in range(args.rounds):
                for what in ("off", "record", "ros2"):
                    side = None
                    if what == "record":
                        side = procs.start(["record", "-o", str(tmp / f"run{rnd}.mcap")], procs.bus_env(endpoint),
                                           tmp / f"record{rnd}.log")
                    elif what == "ros2":
                        side = procs.start(["ros2"], procs.bus_env(endpoint), tmp / f"ros2-{rnd}.log")
                    if side is not None:
                        procs.wait_alive(s, "car0", what, proc=side)
                        c0, t0 = _cpu_s(side.pid), time.monotonic()
                    e2e, n_lost = end_to_end(["policy"], msgs, args.scans, args.rate_hz, endpoint,
                                             tmp / f"policy-{what}-{rnd}.log")
                    lat[what].extend(e2e.tolist())
                    lost[what] += n_lost
                    if side is not None:
                        cpu[what].append((_cpu_s(side.pid) - c0) / (time.monotonic() - t0))
                        procs.stop(side)
    load1 = os.getloadavg()
    ip = in_process(args.reps, tmp)

    res = {"e2e_ms": {k: summarize(np.array(v), 1e3) for k, v in lat.items()}, "lost": lost,
           "cpu_fraction": {k: float(np.mean(v)) for k, v in cpu.items()}, "in_process_us": ip,
           "loadavg_start": load0, "loadavg_end": load1}
    rows = []
    for k, label in (("off", "nothing else on the bus"), ("record", "racecav record (everything of the car)"),
                     ("ros2", "racecav ros2 (rmw_zenoh mirror)")):
        e = res["e2e_ms"][k]
        c = f"{100 * res['cpu_fraction'][k]:.1f} %" if k in res["cpu_fraction"] else ""
        rows.append([label, f"{e['median']:.3f}", f"{e['p99']:.3f}", e["n"], lost[k], c])
    d_rec = res["e2e_ms"]["record"]["median"] - res["e2e_ms"]["off"]["median"]
    d_ros = res["e2e_ms"]["ros2"]["median"] - res["e2e_ms"]["off"]["median"]
    md = "\n".join([
        table(rows, ["beside the policy", "scan -> command ms median", "p99", "scans", "lost",
                     "CPU of the extra process (one core)"]), "",
        table([[k, f"{v['median']:.1f}", f"{v['p99']:.1f}"] for k, v in ip.items()],
              ["in-process, per message", "us median", "p99"]), "",
        f"End to end as in `racecav bench controllers` (the policy, client mode through a local router): "
        f"{args.scans} scans (with their states) at {args.rate_hz:g} Hz per run, {args.rounds} rounds of "
        f"(off, record, ros2). The recorder and the mirror are separate processes subscribed to the "
        f"same keys (the router fans the samples out; the controller's path never waits for them), at "
        f"niceness +10, doing their work in batches (every 50 ms / 10 ms). Median change over nothing "
        f"else on the bus: record {d_rec:+.3f} ms, ros2 {d_ros:+.3f} ms: what is left is the router's "
        f"extra fan-out and the extra process's network threads sharing 2 cores. "
        f"Load average {load0[0]:.1f} -> {load1[0]:.1f} on {os.cpu_count()} cores (a shared machine: "
        f"compare within one run).",
    ])
    print(md)
    dump_json(args.json, res)
    if not args.no_doc:
        write_section("record", "racecav bench record", md)
    return 0
