"""``racecav bench sim``: how fast the PyBullet reference world runs, and the sim service.

1. Control steps per second (4 physics substeps of 25 ms + lidar + traffic driver) of the 16-car
   racetrack, with the lidar cast for the agent only and for all 16 cars, in this process.
2. The sim service as a separate process on a router, racetrack scenario, driven by the scripted
   controller: the real-time factor it achieves when asked for 1.0 and when unthrottled
   (``--real-time-factor 0``), and its lockstep rate (control steps per second with the
   controller's round trip over Zenoh in every step).
Reference on this machine kind (measurements.md): ~170 (agent lidar) and ~60 (all lidars).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from racecav.common.bench import dump_json, summarize, table, write_section
from racecav.common.config import Config


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--steps", type=int, default=400, help="control steps timed per world variant")
    p.add_argument("--seconds", type=float, default=6.0, help="wall seconds per sim-service run")
    p.add_argument("--no-service", action="store_true", help="only the in-process world rates")


def world_rate(lidar_all: bool, steps: int, seed: int = 0) -> dict:
    """Time ``steps`` control steps of the 16-car racetrack (resets excluded)."""
    from tqdm import tqdm

    from racecav.sim.bullet_world import BulletWorld

    with BulletWorld("racetrack", lidar_all=lidar_all) as w:
        w.reset(seed=seed)
        rng = np.random.default_rng(seed)
        for _ in range(20):  # warm-up
            w.step([0.6, 0.0])
        t = np.empty(steps)
        for i in tqdm(range(steps), desc=f"racetrack lidar {'all' if lidar_all else 'agent'}", leave=False):
            a = [rng.uniform(0.3, 1.0), rng.uniform(-0.3, 0.3)]
            t0 = time.perf_counter_ns()
            _, _, collided, _ = w.step(a)
            t[i] = time.perf_counter_ns() - t0
            if collided[0]:
                w.reset()
    s = summarize(t, 1e-6)  # ms
    s["steps_per_s"] = 1000.0 / s["mean"]
    return s


def service_run(args_sim: list[str], seconds: float) -> dict:
    """Run router + sim service + scripted controller for ``seconds``; the sim's status then."""
    from racecav.common import procs
    from racecav.common.client import get_status, open_session
    from racecav.common.config import load_config

    with procs.router() as endpoint:
        env = procs.bus_env(endpoint)
        sim = procs.start(["sim", *args_sim], env)
        ctl = None
        try:
            cfg = load_config(environ={"RACECAV_BUS__CONNECT": f'["{endpoint}"]'})
            with open_session(cfg) as s:
                procs.wait_alive(s, cfg.bus.car, "sim", proc=sim)
                # the agent stays parked (no crash, no episode resets in the window): 16 cars
                # still simulate, the traffic queues behind it
                ctl = procs.start(["scripted", "--program", "0.0,0.0,1000000"], env)
                procs.wait_alive(s, cfg.bus.car, "scripted", proc=ctl)
                st0 = get_status(s, cfg.bus.car, "sim").info
                w0 = time.monotonic()
                time.sleep(seconds)
                st1 = get_status(s, cfg.bus.car, "sim").info
                wall = time.monotonic() - w0
        finally:
            if ctl is not None:
                procs.stop(ctl)
            procs.stop(sim)
    # sim time over wall time across episodes: steps x period (episodes may reset)
    steps = st1["seq"] - st0["seq"]
    return {"steps": steps, "wall_s": wall, "steps_per_s": steps / wall,
            "real_time_factor": steps * 0.1 / wall, "status": st1}


def run(args: argparse.Namespace, cfg: Config) -> int:
    from racecav.common.vehicle import load_car

    import os

    period = load_car().control_period_s
    res: dict = {"control_period_s": period, "load_avg_before": os.getloadavg()[0]}
    res["world_lidar_agent"] = world_rate(False, args.steps)
    res["world_lidar_all"] = world_rate(True, args.steps)
    rows = [["16-car racetrack, lidar on the agent only", f"{res['world_lidar_agent']['steps_per_s']:.0f}",
             f"{res['world_lidar_agent']['median']:.2f}", f"{res['world_lidar_agent']['p99']:.2f}",
             f"{res['world_lidar_agent']['steps_per_s'] * period:.1f}"],
            ["16-car racetrack, lidar on all 16 cars", f"{res['world_lidar_all']['steps_per_s']:.0f}",
             f"{res['world_lidar_all']['median']:.2f}", f"{res['world_lidar_all']['p99']:.2f}",
             f"{res['world_lidar_all']['steps_per_s'] * period:.1f}"]]
    ratio = res["world_lidar_agent"]["steps_per_s"] / res["world_lidar_all"]["steps_per_s"]
    md = ("In-process PyBullet world (`BulletWorld`), one control step = 4 physics substeps of 25 ms, "
          "traffic driver, lidar (170 rays per car, one rayTestBatch). "
          f"Load average before the run: {res['load_avg_before']:.2f} (the machine is shared); "
          f"agent-only / all-lidar ratio in this run: {ratio:.1f}x.\n\n"
          + table(rows, ["world", "control steps/s", "median ms", "p99 ms", "x real time (0.1 s steps)"]))
    if not args.no_service:
        common = ["--racetrack", "--on-end", "reset"]
        for name, extra in (("service_rtf1", ["--real-time-factor", "1"]),
                            ("service_unthrottled", ["--real-time-factor", "0"]),
                            ("service_lockstep", ["--mode", "lockstep"])):
            r = service_run([*common, *extra], args.seconds)
            res[name] = {k: v for k, v in r.items() if k != "status"}
            res[name]["watchdog_brakes"] = r["status"].get("watchdog_brakes")
        srows = [["realtime, real-time factor 1 requested", f"{res['service_rtf1']['real_time_factor']:.2f}",
                  f"{res['service_rtf1']['steps_per_s']:.0f}"],
                 ["realtime, unthrottled (factor 0)", f"{res['service_unthrottled']['real_time_factor']:.2f}",
                  f"{res['service_unthrottled']['steps_per_s']:.0f}"],
                 ["lockstep with the scripted controller over Zenoh", f"{res['service_lockstep']['real_time_factor']:.2f}",
                  f"{res['service_lockstep']['steps_per_s']:.0f}"]]
        md += ("\n\nThe sim service (`racecav sim --racetrack`, separate process, router, scripted controller "
               f"answering every scan with a parked-agent command), {args.seconds:.0f} s each; real-time factor = sim time / wall time.\n\n"
               + table(srows, ["sim service", "real-time factor", "control steps/s"]))
    print(md)
    dump_json(args.json, res)
    if not args.no_doc:
        write_section("sim", "racecav bench sim", md)
    return 0
