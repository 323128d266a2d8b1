"""``racecav record`` / ``racecav replay``: one MCAP file per run that ROS tools can read, and a
recorded lockstep run replayed into a fresh policy gives the same commands (and a different
policy is caught)."""

from __future__ import annotations

import math
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mcap")
pytest.importorskip("rosbags")

from racecav.common import keys, procs  # noqa: E402
from racecav.common.client import get_status  # noqa: E402
from racecav.common.codec import decode, encode  # noqa: E402
from racecav.common.messages import DriveCommand, Scan, VehicleState  # noqa: E402
from racecav.services.record.mcapfile import RAW_SCHEMA, RunFileError, RunWriter, read_raw  # noqa: E402
from racecav.services.record.replay import load_run  # noqa: E402
from tests.test_controllers_policy import random_policy_file  # noqa: E402

# 10 s on an empty road: the run lasts its full duration whatever the policy does (no obstacle).
TEN_SECONDS = """
name = "empty-road-10s"
world = "intersection"
duration_s = 10.0
[ego]
x = -6.0
y = 0.0
yaw_deg = 0.0
speed = 1.0
[success]
min_progress_m = 1.0
"""


def _scan(seq: int) -> Scan:
    r = np.linspace(0.5, 11.0, 170, dtype=np.float32)
    r[3] = np.inf
    return Scan(stamp_ns=100_000_000 * seq, seq=seq, source="sim", angle_min=-math.pi / 4,
                angle_max=math.pi / 4, angle_increment=math.pi / 2 / 169, range_min=0.1, range_max=12.0,
                ranges=r)


def test_run_file_layout_is_read_by_ros_tools(tmp_path):
    """Raw samples come back byte for byte; the ROS copies decode with mcap-ros2-support's
    dynamic decoder (built from the ros2msg schema text, not rosbags) and with rosbags'
    reader (what `ros2 bag`'s MCAP storage reads); garbage on a key is kept raw, not copied."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path = tmp_path / "run.mcap"
    w = RunWriter(path, "car0")
    sent = []
    for i in range(3):
        sent.append(("racecav/car0/scan", encode(_scan(i))))
        sent.append(("racecav/car0/state", encode(VehicleState(stamp_ns=i, source="sim", x=i, y=1.0, yaw=0.3, vx=1.0))))
        sent.append(("racecav/car0/cmd", encode(DriveCommand(stamp_ns=i, source="policy", a_throttle=0.5, a_steer=-0.2,
                                                             throttle=0.5, steering_angle=-0.05, scan_seq=i))))
    sent.append(("racecav/car0/estop", b"stop"))
    sent.append(("racecav/car0/scan", b"\x93garbage"))
    for n, (k, p) in enumerate(sent):
        w.write(k, p, 1_000_000_000 + n)
    w.close()

    raw = read_raw(path)
    assert [(s.key, s.payload) for s in raw] == sent

    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        chans = {c.topic: c for c in summary.channels.values()}
        # every channel is CDR with its ros2msg schema in the file: nothing Foxglove or rosbag2
        # cannot decode (no custom encoding, no schema-less channel)
        assert {c.message_encoding for c in chans.values()} == {"cdr"}
        assert {summary.schemas[c.schema_id].encoding for c in chans.values()} == {"ros2msg"}
        assert summary.schemas[chans["racecav/car0/scan"].schema_id].name == RAW_SCHEMA
        assert "offered_qos_profiles" in chans["/scan"].metadata
        decoded = {}
        for _s, ch, m, msg in reader.iter_decoded_messages():
            decoded.setdefault(ch.topic, []).append((m.log_time, msg))
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    raw_scan = decoded["racecav/car0/scan"][0][1]
    assert bytes(raw_scan.payload) == sent[0][1]  # the raw sample, byte for byte, by its schema alone
    # the frame tree: base_link -> laser from the car file's mount, once, at the first message;
    # odom -> base_link at every state's pose and stamp
    from racecav.common.vehicle import load_car

    (t_static, tf_static), = decoded["/tf_static"]
    mount = load_car("slash").lidar_mount
    tr = tf_static.transforms[0]
    assert (tr.header.frame_id, tr.child_frame_id) == ("base_link", "laser") and t_static == 1_000_000_000
    assert (tr.transform.translation.x, tr.transform.translation.z) == (mount.x, mount.z)
    tfs = [m.transforms[0] for _t, m in decoded["/tf"]]
    assert [(t.header.frame_id, t.child_frame_id, t.transform.translation.x, t.header.stamp.nanosec)
            for t in tfs] == [("odom", "base_link", float(i), i) for i in range(3)]
    # header stamps are the messages' own stamps
    assert [m.header.stamp.nanosec for _t, m in decoded["/scan"]] == [_scan(i).stamp_ns for i in range(3)]
    decoded = {t: [m for _t, m in v] for t, v in decoded.items()}
    assert meta["racecav"]["car"] == "car0"
    assert len(decoded["/scan"]) == 3  # the garbage scan got no copy
    assert np.array_equal(np.asarray(decoded["/scan"][1].ranges, np.float32), _scan(1).ranges)
    assert decoded["/odom"][2].pose.pose.position.x == 2.0
    assert decoded["/drive"][0].drive.steering_angle == pytest.approx(-0.05)

    from racecav.services.record.plot import plot_run

    assert plot_run(path, tmp_path / "run.png").stat().st_size > 10_000

    from rosbags.highlevel import AnyReader

    with AnyReader([path]) as r:
        conns = {c.topic: c for c in r.connections}
        assert conns["/scan"].msgtype == "sensor_msgs/msg/LaserScan" and conns["/scan"].msgcount == 3
        _c, _t, data = next(iter(r.messages(connections=[conns["/odom"]])))
        assert r.deserialize(data, "nav_msgs/msg/Odometry").twist.twist.linear.x == 1.0
        assert conns["racecav/car0/estop"].msgtype == RAW_SCHEMA  # rosbags reads the raw channels too
        _c, _t, data = next(iter(r.messages(connections=[conns["racecav/car0/estop"]])))
        assert bytes(r.deserialize(data, RAW_SCHEMA).payload) == b"stop"


def _replay(env, *args) -> subprocess.CompletedProcess:
    return subprocess.run(procs.racecav_cmd("replay", *args), env=env, capture_output=True, text=True, timeout=120)


def test_bad_run_files_are_named(tmp_path, router):
    env = procs.bus_env(router)
    missing = tmp_path / "nope.mcap"
    r = _replay(env, str(missing))
    assert r.returncode == 2 and str(missing) in r.stdout and "no such file" in r.stdout
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"not an mcap file at all" * 10)
    r = _replay(env, str(garbage))
    assert r.returncode == 2 and str(garbage) in r.stdout
    with pytest.raises(RunFileError, match="cut.mcap"):
        good = tmp_path / "good.mcap"
        w = RunWriter(good, "car0")
        for i in range(50):
            w.write("racecav/car0/scan", encode(_scan(i)))
        w.close()
        (tmp_path / "cut.mcap").write_bytes(good.read_bytes()[: good.stat().st_size // 2])
        read_raw(tmp_path / "cut.mcap")


def _wait(pred, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(0.1)
    raise TimeoutError(what)


def test_lockstep_run_replays_with_identical_commands(spawn, session, router, tmp_path):
    scenario = tmp_path / "ten.toml"
    scenario.write_text(TEN_SECONDS)
    run = tmp_path / "run.mcap"
    rec = spawn("record", "-o", str(run))
    procs.wait_alive(session, "car0", "record", proc=rec)
    sim = spawn("sim", "--scenario", str(scenario), "--mode", "lockstep")
    procs.wait_alive(session, "car0", "sim", proc=sim)
    pol = spawn("policy")
    _wait(lambda: get_status(session, "car0", "sim").info.get("done"), 120, "the 10 s run did not finish")
    procs.stop(pol)
    procs.stop(sim)
    time.sleep(0.3)
    assert procs.stop(rec) == 0

    _car, scans, recorded = load_run(run)
    assert len(scans) >= 95  # 10 s at the 0.1 s control period
    assert scans[-1].stamp_ns - scans[0].stamp_ns >= 9.4e9

    env = procs.bus_env(router)
    fresh = spawn("policy")
    procs.wait_alive(session, "car0", "policy", proc=fresh)
    r = _replay(env, str(run), "--lockstep", "--tolerance", "0", "--json", str(tmp_path / "rep.json"))
    assert r.returncode == 0, r.stdout + r.stderr
    import json

    rep = json.loads((tmp_path / "rep.json").read_text())
    assert rep["scans"] == len(scans) and rep["identical"] == rep["compared"] == rep["answered"] == len(scans)
    # by the recorded stamps, 5x faster: a 10 s run in about 2 s, every scan answered the same way
    t0 = time.monotonic()
    r = _replay(env, str(run), "--rate", "5", "--json", str(tmp_path / "rate.json"))
    rate = json.loads((tmp_path / "rate.json").read_text())
    assert r.returncode == 0 and rate["answered"] >= 0.95 * len(scans) and rate["identical"] == rate["compared"]
    assert time.monotonic() - t0 > 1.9  # paced by the stamps, not as fast as possible
    procs.stop(fresh)

    # other weights on the same scans: the regression check fails and says by how much
    other = spawn("policy", "--model", str(random_policy_file(tmp_path / "other.npz")))
    procs.wait_alive(session, "car0", "policy", proc=other)
    r = _replay(env, str(run), "--lockstep", "--tolerance", "0.001", "--json", str(tmp_path / "rep2.json"))
    rep2 = json.loads((tmp_path / "rep2.json").read_text())
    assert r.returncode == 1 and rep2["identical"] < rep2["compared"] and rep2["a_steer_max_abs_diff"] > 0.001


def test_eval_record_cuts_each_lockstep_trial_exactly(tmp_path):
    """`racecav eval --record DIR` (lockstep): one run file per trial, cut at the episode
    boundary by stamp. Read with an MCAP reader: every channel decodes (no encoding Foxglove
    flags), /tf_static and /tf are there, log times span the trial's sim duration, and the
    scans, states, obstacle states and commands of each trial are exactly its own: all of
    them, and none of another trial nor of setup.mcap (the start-up, recorded first, so it is
    there however far the sim's start scenario ran before the first trial)."""
    import json

    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from racecav.common.messages import ObstacleStates

    out, rec_dir = tmp_path / "eval", tmp_path / "mcap"
    r = subprocess.run(procs.racecav_cmd("eval", "--scenario", "head-to-head", "--controller", "drl-reversed",
                                         "--mode", "lockstep", "--trials", "3", "--record", str(rec_dir),
                                         "--out-dir", str(out), "--no-progress"),
                       capture_output=True, text=True, timeout=400)
    assert r.returncode == 0, r.stdout + r.stderr
    trials = [json.loads(line)["trial"] for line in (out / "head-to-head-drl-reversed.jsonl").read_text().splitlines()]
    names = [f"head-to-head-{t['index']:03d}-seed{t['seed']}.mcap" for t in trials]
    assert len(trials) == 3 and sorted(p.name for p in rec_dir.iterdir()) == sorted(names + ["setup.mcap"])
    # the sim's first scan (its start scenario) is in setup.mcap, and no sample of it in a trial's file
    seen: dict[str, set] = {"state": set(), "scan": set(), "obstacles": set(), "cmd": set()}
    for smp in read_raw(rec_dir / "setup.mcap"):
        leaf = smp.key.rsplit("/", 1)[-1]
        cls = {"state": VehicleState, "scan": Scan, "obstacles": ObstacleStates, "cmd": DriveCommand}.get(leaf)
        if cls is not None:
            msg = decode(smp.payload, cls)
            seen[leaf].add(msg.scan_seq if leaf == "cmd" else msg.seq)
    assert 0 in seen["scan"], "the start scenario's first scan is not in setup.mcap"
    for t, name in zip(trials, names):
        path = rec_dir / name
        with open(path, "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            summary = reader.get_summary()
            chans = summary.channels.values()
            assert {c.message_encoding for c in chans} == {"cdr"}, name
            assert {summary.schemas[c.schema_id].encoding for c in chans} == {"ros2msg"}, name
            topics = {c.topic for c in chans}
            assert {"/tf_static", "/tf", "/scan", "/odom", "/drive"} <= topics, topics
            assert sum(1 for _ in reader.iter_decoded_messages()) == summary.statistics.message_count
        by: dict[str, list] = {k: [] for k in seen}
        for smp in read_raw(path):
            leaf = smp.key.rsplit("/", 1)[-1]
            cls = {"state": VehicleState, "scan": Scan, "obstacles": ObstacleStates, "cmd": DriveCommand}.get(leaf)
            if cls is not None:
                msg = decode(smp.payload, cls)
                assert smp.log_time_ns == msg.stamp_ns  # logged at its own (sim) stamp
                by[leaf].append(msg)
        seqs = {k: {m.scan_seq if k == "cmd" else m.seq for m in v} for k, v in by.items()}
        first = min(seqs["state"])
        trial = set(range(first, first + t["steps"]))
        # exactly the trial's steps (republished scans repeat a seq), the same for scans and obstacles
        assert seqs["state"] == seqs["scan"] == seqs["obstacles"] == trial, (name, len(seqs["state"]), t["steps"])
        # lockstep: every scan but the last was answered, the last one may be; nothing else
        assert set(range(first, first + t["steps"] - 1)) <= seqs["cmd"] <= trial, name
        for k in seen:
            assert not seen[k] & seqs[k], f"{name}: {k} also in another trial's file"
            seen[k] |= seqs[k]
        stamps = [s.stamp_ns for s in by["scan"]]
        assert (max(stamps) - min(stamps)) * 1e-9 == pytest.approx(t["end_time_s"], abs=1e-6)


def test_real_sensor_scans_are_restamped(spawn, session, router, tmp_path):
    """Scans recorded from the real sensor carry that host's (old) monotonic stamps: replay
    re-stamps them as it sends them, or the policy would drop every one as stale. The sensor's
    default scan (wide) holds the default policy's view."""
    import json

    from racecav.common.lidar import WIDE_SCAN, make_scan

    path = tmp_path / "real.mcap"
    w = RunWriter(path, "car0")
    for i in range(20):
        old = make_scan(np.linspace(0.5, 11.0, WIDE_SCAN.n_rays, dtype=np.float32), 1_000 + i * 100_000_000, i,
                        "real", WIDE_SCAN)
        w.write("racecav/car0/scan", encode(old))
    w.close()
    pol = spawn("policy")
    procs.wait_alive(session, "car0", "policy", proc=pol)
    r = _replay(procs.bus_env(router), str(path), "--lockstep", "--json", str(tmp_path / "rep.json"))
    rep = json.loads((tmp_path / "rep.json").read_text())
    assert r.returncode == 0 and rep["answered"] == 20 and rep["recorded_answers"] == 0, r.stdout
