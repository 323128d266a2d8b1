"""``racecav bench controllers``: the paper's Table 2 (computation cost) on this machine.

For the DRL policy (``--model``, the shipped default avoid unless named) and the MPC-APF baseline:

- FLOPs per control step: the MLP counted as the paper does (2 x parameters - 2: 30,466 for the
  paper's 170-64-64-2, 51,970 for avoid's 338-64-64-2); the MPC by casadi's instruction counts times the solver's calls (see
  :meth:`racecav.services.baseline.mpc.MpcApf.flops` and docs/controllers.md), over closed-loop
  steps;
- in-process latency: the policy from the published (wide) scan to action as the service runs it
  (its own view out of the scan, its scan stack, sanitise + normalise + MLP in one compiled
  kernel, services/policy/fused.py), beside the plain-numpy reference path and its MLP alone;
  every shipped policy the same way, each in its own view and stack; the baseline's whole step (ego estimate, perception, MPC) on the steps of
  closed-loop PyBullet episodes (head-to-head, right-to-left, left-to-right, driven by the
  baseline itself);
- end-to-end over Zenoh: a Scan published (with the VehicleState before it, as the sim does)
  through a router -> the controller process -> its DriveCommand received back, per scan (the
  policy gets wide scans, as the sim and the sensor publish them; the baseline its own lidar's).

The machine's load average is printed with the numbers: the reference machine is shared.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from racecav.common import registry

PAPER = registry.PAPER_TABLE2
# head-to-head first: the scenario with the most evasive driving (the baseline's hardest)
SCENARIOS = ("head-to-head", *(s for s in registry.PAPER_SCENARIOS if s != "head-to-head"))


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", default=None, help="policy: a shipped name or a .npz (default: policy.model, "
                   "the shipped avoid)")
    p.add_argument("--reps", type=int, default=3000, help="in-process policy repetitions")
    p.add_argument("--seeds", type=int, default=2, help="closed-loop episodes per scenario for the baseline")
    p.add_argument("--e2e-scans", type=int, default=300, help="scans per controller end to end")
    p.add_argument("--rate-hz", type=float, default=50.0, help="scan rate end to end")


def closed_loop(cfg, seeds: int):
    """Baseline-driven PyBullet episodes: per-step (act seconds, iterations, flops), and the
    (state, scan) messages for the end-to-end replay."""
    from tqdm import tqdm

    from racecav.common.lidar import make_scan
    from racecav.common.messages import VehicleState
    from racecav.common.vehicle import load_car
    from racecav.services.baseline.service import MpcApfController
    from racecav.sim.bullet_world import BulletWorld

    car = load_car(cfg.baseline.car)
    steps, msgs, outcomes = [], [], []
    runs = [(s, k) for s in SCENARIOS for k in range(seeds)]
    # one controller for all episodes, as a running service (it notices each new episode)
    ctl = MpcApfController(car, cfg.baseline)
    deadline = time.monotonic() + 300
    while cfg.baseline.compile and not (ctl.mpc.compiled or ctl.mpc.compile_error) and time.monotonic() < deadline:
        time.sleep(0.1)  # measure the steady state: compiled derivatives (cached after the first run)
    for scen, seed in tqdm(runs, desc="baseline closed loop", unit="episode"):
        with BulletWorld(scen, car=car) as w:
            w.reset(seed=seed)
            for k in range(int(round(w.scenario.duration_s / car.control_period_s))):
                x, y, yaw, vx = w.agent_state()[0]
                stamp = int(round(w.t * 1e9))
                scan = make_scan(w.scan_ranges, stamp, k, "sim", w.spec)
                state = VehicleState(stamp_ns=stamp, seq=k, source="sim", x=x, y=y, yaw=yaw, vx=vx,
                                     steering_angle=float(w.steer[0]))
                t0 = time.perf_counter()
                a = ctl.act(scan, state, time.monotonic_ns())
                dt = time.perf_counter() - t0
                steps.append((dt, ctl.last["iterations"], ctl.last["flops"]))
                msgs.append((state, scan))
                w.step(np.asarray(a))
                if w.collided:
                    break
            outcomes.append((scen, seed, bool(w.success()[0]), w.collided))
    return np.array(steps, dtype=float), msgs, outcomes


def wide_episodes() -> list:
    """(state, scan) of the paper's three scenarios with the published wide scan
    (common/lidar.WIDE_SCAN, what the sim and the sensor publish by default), the ego rolling
    straight from its 1 m/s start: every policy takes its own view out of these."""
    from racecav.common.lidar import WIDE_SCAN, make_scan
    from racecav.common.messages import VehicleState
    from racecav.sim.bullet_world import BulletWorld

    msgs = []
    for scen in SCENARIOS:
        with BulletWorld(scen, lidar=WIDE_SCAN) as w:
            w.reset(seed=0)
            for k in range(int(round(w.scenario.duration_s / w.car.control_period_s))):
                x, y, yaw, vx = w.agent_state()[0]
                stamp = int(round(w.t * 1e9))
                msgs.append((VehicleState(stamp_ns=stamp, seq=k, source="sim", x=x, y=y, yaw=yaw, vx=vx),
                             make_scan(w.scan_ranges, stamp, k, "sim", w.spec)))
                w.step(np.array([[0.0, 0.0]], np.float32))
                if w.collided:
                    break
    return msgs


def _service(cfg, model: str, pol, backend: str = "fused"):
    """The policy service's act path without a bus (its view, its stack, the backend)."""
    from racecav.services.policy.service import PolicyService

    pcfg = cfg.policy.model_copy(update={"model": model, "backend": backend})
    return PolicyService(cfg.model_copy(update={"policy": pcfg}), policy=pol)


def _act_times(svc, scans, reps: int) -> np.ndarray:
    """Seconds per ``svc.act`` over ``reps`` scans, re-stamped as one continuous run (one step
    apart, consecutive seqs: a stacked policy's stack never restarts)."""
    dt = []
    for i in range(reps):
        scan = scans[i % len(scans)].model_copy(update={"seq": i, "stamp_ns": (i + 1) * 100_000_000})
        if not svc.check(scan, time.monotonic_ns()):
            raise RuntimeError(f"{svc.model_ref}: the wide scan was refused: {svc.counts}")
        t0 = time.perf_counter_ns()
        svc.act(scan)
        dt.append(time.perf_counter_ns() - t0)
    return np.array(dt) * 1e-9


def policy_in_process(cfg, model: str, pol, scans, reps: int):
    """Seconds per scan: the service's path with the fused kernel, with the numpy reference
    (sanitise + NumpyPolicy), and the MLP alone on the policy's (stacked) observation."""
    fused = _act_times(_service(cfg, model, pol, "fused"), scans, reps)
    ref = _service(cfg, model, pol, "numpy")
    full = _act_times(ref, scans, reps)
    from racecav.common.lidar import sanitize

    obs = sanitize(ref.stack.current() if ref.stack.n > 1 else ref.view(scans[0]), ref.spec)
    mlp = []
    for _ in range(reps):
        t0 = time.perf_counter_ns()
        pol(obs)
        mlp.append(time.perf_counter_ns() - t0)
    return fused, full, np.array(mlp) * 1e-9


def end_to_end(args_cmd: list[str], msgs, n: int, rate_hz: float, endpoint: str, log: Path,
               mode: str = "client"):
    """Publish n scans (each after its state) and time each until its command comes back.

    :param mode: the bus mode of both ends (client: through the router; peer: direct links).
    """
    from tqdm import tqdm

    from racecav.common import keys, procs
    from racecav.common.client import open_session
    from racecav.common.codec import decode, encode
    from racecav.common.config import load_config
    from racecav.common.messages import DriveCommand

    mode_env = {"RACECAV_BUS__MODE": mode}
    cfg = load_config(environ={"RACECAV_BUS__CONNECT": f'["{endpoint}"]', **mode_env})
    sent: dict[int, int] = {}
    lat: list[float] = []
    lock = threading.Lock()

    def on_cmd(sample):
        t = time.perf_counter_ns()
        cmd = decode(sample.payload.to_bytes(), DriveCommand)
        with lock:
            t0 = sent.pop(cmd.scan_seq, None)
            if t0 is not None:
                lat.append((t - t0) * 1e-9)

    proc = procs.start(args_cmd, procs.bus_env(endpoint, extra=mode_env), log)
    name = args_cmd[0]
    try:
        with open_session(cfg) as s:
            procs.wait_alive(s, "car0", name, proc=proc)
            if name == "baseline":  # steady state: wait until its solver is compiled (cached)
                from racecav.common.client import get_status

                deadline = time.monotonic() + 300
                while time.monotonic() < deadline:
                    info = get_status(s, "car0", name).info
                    if info.get("compiled") or info.get("compile_error"):
                        break
                    time.sleep(0.2)
            sub = s.declare_subscriber(keys.topic("car0", keys.CMD), on_cmd)
            # like the sim's publishers; scans express (no batching delay)
            pub_scan = s.declare_publisher(keys.topic("car0", keys.SCAN), express=True)
            pub_state = s.declare_publisher(keys.topic("car0", keys.STATE), express=True)
            period = 1.0 / rate_hz
            t_next = time.perf_counter()
            base_stamp = 0
            time.sleep(0.5)  # peer mode: let the direct link form before timing
            for i in tqdm(range(n + 20), desc=f"end to end: {name} ({mode})", unit="scan"):
                state, scan = msgs[i % len(msgs)]
                # one continuous run: stamps keep increasing, sequence numbers are unique
                stamp = base_stamp + i * 100_000_000
                st = state.model_copy(update={"stamp_ns": stamp, "seq": i})
                sc = scan.model_copy(update={"stamp_ns": stamp, "seq": i})
                pub_state.put(encode(st))
                data = encode(sc)
                with lock:
                    if i >= 20:  # the first 20 warm up the path
                        sent[i] = time.perf_counter_ns()
                pub_scan.put(data)
                t_next += period
                time.sleep(max(0.0, t_next - time.perf_counter()))
            time.sleep(0.3)
            lost = len(sent)
            sub.undeclare()
            pub_scan.undeclare()
            pub_state.undeclare()
    finally:
        procs.stop(proc)
    return np.array(lat), lost


def shipped_in_service(cfg, scans, reps: int) -> dict[str, dict]:
    """Seconds per scan of each shipped policy's service act path (its view out of the published
    wide scan, its scan stack, the fused kernel: what ``compute_ns`` covers)."""
    from racecav.common.policy import MODELS_DIR, SHIPPED, load_policy

    out = {}
    for name in SHIPPED:
        if not (MODELS_DIR / f"{name}.npz").is_file():
            continue
        pol = load_policy(name)
        out[name] = {"inputs": pol.obs_dim, "lidar": pol.metadata.get("lidar", "paper"), "stack": pol.obs_stack,
                     "flops": 2 * pol.n_params - 2, "dt": _act_times(_service(cfg, name, pol), scans, reps)}
    return out


def run(args: argparse.Namespace, cfg) -> int:
    from racecav.common import procs
    from racecav.common.bench import dump_json, summarize, table, write_section
    from racecav.common.policy import load_policy

    tmp = Path(tempfile.mkdtemp(prefix="racecav-bench-"))
    model_ref = args.model or cfg.policy.model
    pol = load_policy(model_ref)
    view, stack = pol.metadata.get("lidar", "paper"), pol.obs_stack
    model_desc = f"{model_ref} ({view} view, {pol.lidar.n_rays} rays x {stack} scan{'s' if stack > 1 else ''})"
    load0 = os.getloadavg()

    steps, msgs, outcomes = closed_loop(cfg, args.seeds)
    wide = wide_episodes()
    fused, full, mlp = policy_in_process(cfg, model_ref, pol, [m[1] for m in wide], args.reps)
    shipped = shipped_in_service(cfg, [m[1] for m in wide], args.reps)
    with procs.router(log_path=tmp / "router.log") as endpoint:
        pol_e2e, pol_lost = end_to_end(["policy", "--model", model_ref], wide, args.e2e_scans, args.rate_hz,
                                       endpoint, tmp / "policy.log")
        peer_e2e, peer_lost = end_to_end(["policy", "--model", model_ref], wide, args.e2e_scans,
                                         args.rate_hz, endpoint, tmp / "policy-peer.log", mode="peer")
        base_e2e, base_lost = end_to_end(["baseline"], msgs, args.e2e_scans, args.rate_hz, endpoint,
                                         tmp / "baseline.log")
    load1 = os.getloadavg()

    mlp_flops = 2 * pol.n_params - 2
    res = {
        "policy": {"model": model_desc, "params": pol.n_params, "flops": mlp_flops,
                   "in_process_ms": summarize(fused, 1e3), "numpy_ms": summarize(full, 1e3),
                   "mlp_only_ms": summarize(mlp, 1e3),
                   "e2e_ms": summarize(pol_e2e, 1e3), "e2e_lost": pol_lost,
                   "e2e_peer_ms": summarize(peer_e2e, 1e3), "e2e_peer_lost": peer_lost},
        "baseline": {"flops": summarize(steps[:, 2]), "iterations": summarize(steps[:, 1]),
                     "in_process_ms": summarize(steps[:, 0], 1e3), "e2e_ms": summarize(base_e2e, 1e3),
                     "e2e_lost": base_lost, "steps": len(steps),
                     "episodes": [dict(scenario=s, seed=k, success=bool(ok), collided=bool(c))
                                  for s, k, ok, c in outcomes],
                     "horizon": cfg.baseline.horizon, "dt": cfg.baseline.dt, "solver": cfg.baseline.solver},
        "shipped_in_service": {n: {**{k: v for k, v in d.items() if k != "dt"}, "act_ms": summarize(d["dt"], 1e3)}
                               for n, d in shipped.items()},
        "paper": PAPER, "loadavg_start": load0, "loadavg_end": load1,
    }
    p, b = res["policy"], res["baseline"]

    def ms(d, k="median"):
        return f"{d[k]:.3f}" if d.get("n") else "n/a"

    rows = [
        [f"DRL policy {model_ref} (MLP {pol.obs_dim}-64-64-2)", f"{mlp_flops:,}", f"{ms(p['in_process_ms'])} / {ms(p['in_process_ms'], 'p99')}",
         f"{ms(p['numpy_ms'])} / {ms(p['numpy_ms'], 'p99')}", f"{ms(p['e2e_ms'])} / {ms(p['e2e_ms'], 'p99')}",
         "30,466", "0.206"],
        ["DRL policy, bus in peer mode", "", "", "", f"{ms(p['e2e_peer_ms'])} / {ms(p['e2e_peer_ms'], 'p99')}",
         "", ""],
        [f"MPC-APF (N={cfg.baseline.horizon}, {cfg.baseline.solver})",
         f"{b['flops']['mean']:,.0f} (p99 {b['flops']['p99']:,.0f})",
         f"{ms(b['in_process_ms'])} / {ms(b['in_process_ms'], 'p99')}",
         f"{b['iterations']['mean']:.2f} it. (p99 {b['iterations']['p99']:.0f})",
         f"{ms(b['e2e_ms'])} / {ms(b['e2e_ms'], 'p99')}", "960,000", "13.2 (12 it.)"],
    ]
    header = ["controller", "FLOPs / step (mean)", "in-process ms median / p99", "numpy reference ms / MPC iterations",
              "end-to-end ms median / p99", "paper FLOPs", "paper ms (Jetson Orin)"]
    ratio_f = b["flops"]["mean"] / mlp_flops
    ratio_t = b["in_process_ms"]["median"] / p["in_process_ms"]["median"]
    def e2e_ok(d):
        return f"median <= 0.5 ms: **{d.get('median', 9) <= 0.5}**, p99 <= 1.5 ms: **{d.get('p99', 9) <= 1.5}**"

    targets = (f"Targets: policy in-process median <= 0.010 ms: **{p['in_process_ms']['median'] <= 0.010}**; "
               f"policy end to end, client mode (through the router): {e2e_ok(p['e2e_ms'])}; "
               f"peer mode (direct links): {e2e_ok(p['e2e_peer_ms'])}.")
    srows = [[n, d["lidar"], str(d["stack"]), str(d["inputs"]), f"{d['flops']:,}",
              f"{ms(d['act_ms'])} / {ms(d['act_ms'], 'p99')}", f"**{d['act_ms']['median'] <= 0.010}**"]
             for n, d in res["shipped_in_service"].items()]
    md = "\n".join([
        table(rows, header), "",
        f"MPC-APF / MLP on this machine: {ratio_f:.0f}x the FLOPs, {ratio_t:.0f}x the in-process time "
        f"(paper: 31x, 64x).", "",
        targets, "",
        f"Policy: {model_desc}; in-process = the service's act path on {args.reps} wide scans of the three "
        f"scenarios (its view out of the published scan, its scan stack, sanitise + normalise + MLP in the "
        f"compiled kernel); numpy reference = the same path in plain numpy (its MLP alone: "
        f"{ms(p['mlp_only_ms'])} ms); end to end it gets the same wide scans. Paper columns: the paper's "
        f"170-64-64-2 MLP. "
        f"MPC-APF: {b['steps']} closed-loop steps of {len(outcomes)} PyBullet episodes "
        f"({', '.join(SCENARIOS)}; the baseline driving, lidar perception, state key for ego state); "
        f"in-process = the whole step (ego estimate, perception, MPC; derivative functions compiled to C: "
        f"{cfg.baseline.compile}). FLOPs: casadi instruction counts "
        f"x calls + convexification 9n^3 + QP (4/3)(n+m)^3 per SQP iteration (docs/controllers.md). "
        f"End to end: {args.e2e_scans} scans at {args.rate_hz:g} Hz through a local router, publish -> "
        f"command received, both ends clients of the router (the default) or, for the policy, both "
        f"peers linked directly (`RACECAV_BUS__MODE=peer`; lost: policy {pol_lost}, peer {peer_lost}, "
        f"baseline {base_lost}). Load average "
        f"{load0[0]:.1f} -> {load1[0]:.1f} on {os.cpu_count()} cores (a shared machine: absolute times "
        "are pessimistic, compare the ratios).", "",
        "Every shipped policy's service path in-process: `PolicyService.act` (the policy's view out of the "
        f"published wide scan, its scan stack, the fused kernel: what a command's `compute_ns` covers), {args.reps} "
        "wide scans of the three scenarios (the ego rolling straight from its 1 m/s start) back to back. "
        "In a running service the same path measures 4-5x more (`compute_ns`, the compute column of "
        "docs/results.md), most likely from cold caches: between two scans the router and the sim run "
        "on the same two cores (not measured).", "",
        table(srows, ["policy", "lidar view", "scans stacked", "inputs", "FLOPs", "act ms median / p99",
                      "median <= 0.010 ms"]),
    ])
    print(md)
    dump_json(args.json, res)
    if not args.no_doc:
        write_section("controllers", "racecav bench controllers", md)
    return 0
