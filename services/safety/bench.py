"""``racecav bench safety``: what the supervisor costs and how often it brakes for nothing.

1. Latency (real processes): a router and ``racecav safety``; this process publishes a closing
   wall (VehicleState at 2 m/s, then a Scan, at 10 Hz) and times each scan's publication to the
   arrival of the brake command answering it (same clock: this process). That is the latency the
   supervisor adds on the brake path (scan -> brake, in parallel to scan -> controller), before
   the actuator's own forwarding (``racecav bench vesc``).
2. False brakes (in process, the fast training world, shadow mode): a driver laps the empty
   racetrack and figure eight; the brake logic of several settings judges every scan from the
   true speed and steering angle but never acts. A brake onset is true when the car touches a
   wall within ``--horizon`` s after it (the world then restarts that env), false otherwise.
   Drivers: :data:`DRIVERS`.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from racecav.common import bench as B

VARIANTS = (("none", 0.4), ("straight", 0.4), ("arc", 0.3), ("arc", 0.4), ("arc", 0.5))
"""(path_gate, threshold_s) settings judged side by side in the false-brake measurement."""
DRIVERS = (("racing", 1.0), ("racing", 1.5), ("centerline", 1.0))
"""(driver, agent speed scale): the racing policy at its training speed (top 1.8 m/s) and at the
sim's and actuator's agent scale (top 2.7 m/s, where it also crashes now and then), and the
centerline pure pursuit."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--laps", type=float, default=100.0, help="laps-worth of driving per world and driver")
    p.add_argument("--envs", type=int, default=8, help="worlds stepped together")
    p.add_argument("--horizon", type=float, default=1.5, help="s: a brake followed by contact within this is true")
    p.add_argument("--samples", type=int, default=300, help="latency samples")
    p.add_argument("--skip-latency", action="store_true")
    p.add_argument("--skip-false", action="store_true")


# ------------------------------------------------------------------------------- false brakes
def _centerline_action(fw, out: np.ndarray) -> np.ndarray:
    from racecav.sim import fast_kernels as K

    fw.vfac[:, 0] = 1.0
    fw.lane_offset[:, 0] = 0.0
    car = fw.car
    K.pure_pursuit(fw.x, fw.y, fw.yaw, fw.v, fw.active, fw.cl_idx, fw.lane_offset, fw.vfac, fw.cl, fw.cl_ds,
                   car.wheelbase, car.steer_gain, car.v_max, 3.0, car.width, 0, 1, out)
    return out[:, 0]


def false_brakes(world: str, driver: str, laps: float, n_envs: int, horizon_s: float, speed_scale: float = 1.0,
                 seed: int = 0) -> dict:
    """Shadow-mode brake decisions of every :data:`VARIANTS` setting while ``driver`` laps ``world``."""
    from tqdm import tqdm

    from racecav.common.config import SafetyConfig
    from racecav.common.vehicle import load_car
    from racecav.services.safety.ttc import BrakeLogic
    from racecav.training.env import env_settings, make_world

    fw = make_world(env_settings(world=world, n_obstacles=0, agent_speed_scale=speed_scale), n_envs=n_envs, seed=seed)
    car = load_car()
    fw.reset(seed=seed)
    lap = len(fw.cl) * fw.cl_ds
    policy = None
    if driver != "centerline":
        from racecav.common.policy import load_policy

        policy = load_policy(driver)
    out = np.zeros((n_envs, fw.x.shape[1], 2))
    logics = [[BrakeLogic(SafetyConfig(path_gate=g, threshold_s=t), car) for _ in range(n_envs)]
              for g, t in VARIANTS]
    geom = logics[0][0].geometry(car.lidar.angle_min, car.lidar.angle_increment, car.lidar.n_rays)
    open_onsets: list[list[tuple[int, int]]] = [[] for _ in VARIANTS]   # (env, step)
    true_b, false_b = [0] * len(VARIANTS), [0] * len(VARIANTS)
    hz = int(round(horizon_s / fw.control_period))
    dist, contacts, step = 0.0, 0, 0
    target = laps * lap
    with tqdm(total=round(target), desc=f"{world}/{driver}@{speed_scale:g}", unit="m", leave=False) as bar:
        while dist < target:
            act = policy(fw.agent_obs()) if policy is not None else _centerline_action(fw, out)
            _, _, collided, _ = fw.step(act)
            step += 1
            moved = float(np.abs(fw.v[:, 0]).sum() * fw.control_period)
            dist += moved
            bar.update(moved)
            t_s = step * fw.control_period
            for k, per_env in enumerate(logics):
                for e in range(n_envs):
                    lg = per_env[e]
                    before = lg.brakes
                    lg.update(geom, fw.ranges[e, 0], float(fw.v[e, 0]), t_s, float(fw.delta[e, 0]))
                    if lg.brakes > before:
                        open_onsets[k].append((e, step))
            hit = set(np.flatnonzero(collided).tolist())
            contacts += len(hit)
            for k in range(len(VARIANTS)):
                keep = []
                for e, s0 in open_onsets[k]:
                    if e in hit:
                        true_b[k] += 1
                    elif step - s0 >= hz:
                        false_b[k] += 1
                    else:
                        keep.append((e, s0))
                open_onsets[k] = keep
            if hit:
                fw.reset_worlds(np.array(sorted(hit)))
                for per_env in logics:
                    for e in hit:
                        per_env[e] = BrakeLogic(per_env[e].cfg, car)
    for k in range(len(VARIANTS)):  # onsets still open at the end: no contact followed
        false_b[k] += len(open_onsets[k])
    return {"world": world, "driver": driver, "speed_scale": speed_scale, "laps": dist / lap, "km": dist / 1000, "contacts": contacts,
            "hours": step * fw.control_period * n_envs / 3600,
            "variants": [{"gate": g, "threshold_s": t, "brakes": true_b[k] + false_b[k], "true": true_b[k],
                          "false": false_b[k]} for k, (g, t) in enumerate(VARIANTS)]}


# ------------------------------------------------------------------------------- latency
def latency(samples: int) -> dict:
    import threading

    from racecav.common import keys, procs
    from racecav.common.client import open_session
    from racecav.common.codec import decode, encode
    from racecav.common.config import load_config
    from racecav.common.lidar import make_scan
    from racecav.common.messages import DriveCommand, VehicleState
    from racecav.common.vehicle import load_car

    car = load_car()
    spec = car.lidar
    arrivals: dict[int, int] = {}
    cond = threading.Condition()

    def on_brake(sample) -> None:
        t = time.monotonic_ns()
        msg = decode(sample.payload.to_bytes(), DriveCommand)
        with cond:
            arrivals[msg.scan_seq] = t
            cond.notify_all()

    with procs.router() as ep:
        s = open_session(load_config(environ={"RACECAV_BUS__CONNECT": f'["{ep}"]'}))
        p = procs.start(["safety"], procs.bus_env(ep))
        try:
            procs.wait_alive(s, "car0", "safety", 60, p)
            sub = s.declare_subscriber(keys.topic("car0", keys.SAFETY), on_brake)
            pub_scan = s.declare_publisher(keys.topic("car0", keys.SCAN), express=True)
            pub_state = s.declare_publisher(keys.topic("car0", keys.STATE), express=True)
            ranges = np.full(spec.n_rays, 0.6, np.float32)  # a wall 0.5 m ahead of the bumper at 2 m/s
            sent: dict[int, int] = {}
            time.sleep(0.5)
            for k in range(samples + 5):
                stamp = time.monotonic_ns()
                pub_state.put(encode(VehicleState(stamp_ns=stamp, seq=k, source="sim", x=0.0, y=0.0, yaw=0.0, vx=2.0)))
                sent[k] = time.monotonic_ns()
                pub_scan.put(encode(make_scan(ranges, stamp, k, "sim", spec)))
                with cond:
                    cond.wait_for(lambda: k in arrivals, 0.1)
                time.sleep(max(0.0, 0.1 - (time.monotonic_ns() - stamp) * 1e-9))
            sub.undeclare()
            pub_scan.undeclare()
            pub_state.undeclare()
        finally:
            procs.stop(p)
            s.close()
    lat = [(arrivals[k] - sent[k]) * 1e-6 for k in sent if k in arrivals and k >= 5]
    return {"latency_ms": B.summarize(lat), "braked_scans": len(lat), "sent": samples}


def run(args: argparse.Namespace, cfg) -> int:
    res: dict = {}
    md = []
    if not args.skip_latency:
        res["latency"] = latency(args.samples)
        L = res["latency"]["latency_ms"]
        md.append("Scan -> brake command (racecav safety, real router, 10 Hz, judged in the subscriber "
                  "callback), timed by the publisher:\n\n" + B.table(
                      [[f"{L['median']:.3f}", f"{L['p99']:.3f}", f"{L['max']:.3f}", L["n"]]],
                      ["median (ms)", "p99 (ms)", "max (ms)", "samples"]))
    if not args.skip_false:
        runs = [false_brakes(w, d, args.laps, args.envs, args.horizon, scale)
                for w in ("racetrack", "figure8") for d, scale in DRIVERS]
        res["false_brakes"] = runs
        rows = []
        for r in runs:
            for v in r["variants"]:
                rows.append([r["world"], f"{r['driver']} x{r['speed_scale']:g}", f"{r['laps']:.0f}", r["contacts"], v["gate"], v["threshold_s"],
                             v["false"], v["true"]])
        md.append(f"False brakes in shadow mode (fast world, no obstacle cars; a brake is true when a wall "
                  f"contact follows within {args.horizon} s; contacts: the driver's own crashes, each "
                  "restarting that world):\n\n" + B.table(
                      rows, ["world", "driver", "laps", "contacts", "path gate", "threshold (s)", "false brakes",
                             "true brakes"]))
    B.dump_json(args.json, res)
    text = "\n\n".join(md)
    print(text)
    if not args.no_doc and md:
        B.write_section("safety", "racecav bench safety" + (f" --laps {args.laps:g}" if args.laps != 100 else ""), text)
    return 0
