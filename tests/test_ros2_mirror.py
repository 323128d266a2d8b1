"""``racecav ros2``: what a ROS 2 node on rmw_zenoh (or the DDS bridge) would receive, checked
without ROS: pinned RIHS01 type hashes, data keys, the 33-byte attachment, liveliness tokens, and
CDR payloads decoded by an independent implementation (pycdr2, tests/ros2_cdr.py) and compared
with the racecav messages they mirror; and ROS ``/drive`` arriving as a DriveCommand."""

from __future__ import annotations

import math
import struct
import time

import numpy as np
import pytest
import zenoh

pytest.importorskip("rosbags")

from racecav.common import keys, procs  # noqa: E402
from racecav.common.client import get_status  # noqa: E402
from racecav.common.codec import decode, encode  # noqa: E402
from racecav.common.messages import DriveCommand, Scan, VehicleState  # noqa: E402
from racecav.common.vehicle import load_car, steady_speed  # noqa: E402
from racecav.services.ros2 import msgs  # noqa: E402
from racecav.services.ros2.rmw import Graph, attachment, parse_attachment  # noqa: E402
from tests import ros2_cdr as idl  # noqa: E402

# Known values (ROS 2 Jazzy's type descriptions, as `ros2 interface` / rosidl generate them).
LASER_SCAN_HASH = "RIHS01_64c191398013af96509d518dac71d5164f9382553fce5c1f8cca5be7924bd828"
ACKERMANN_STAMPED_HASH = "RIHS01_48ca7612a08d3bb72744fd98b71b7cf2ea24c6ad50fa4e1aa0bbad963c90d8cf"


def test_type_hashes_are_the_ros_ones():
    assert msgs.type_hash(msgs.LASER_SCAN) == LASER_SCAN_HASH
    assert msgs.type_hash(msgs.ACKERMANN_STAMPED) == ACKERMANN_STAMPED_HASH
    assert msgs.dds_type(msgs.LASER_SCAN) == "sensor_msgs::msg::dds_::LaserScan_"


def test_attachment_layout_is_zenoh_ext_serialisation():
    gid = bytes(range(1, 17))
    a = attachment(7, 1_700_000_000_123_456_789, gid)
    assert len(a) == 33 and a[16] == 16 and a[17:] == gid
    assert struct.unpack_from("<qq", a) == (7, 1_700_000_000_123_456_789)
    # rmw_zenoh writes it with zenoh-ext's serializer: zenoh's own deserializer must agree.
    from zenoh.ext import Int64, z_deserialize

    assert z_deserialize(tuple[Int64, Int64, bytes], zenoh.ZBytes(a)) == (7, 1_700_000_000_123_456_789, gid)
    assert parse_attachment(a) == (7, 1_700_000_000_123_456_789, gid)
    with pytest.raises(ValueError):
        parse_attachment(a[:-1])


def _token_parts(token: str) -> list[str]:
    parts = token.split("/")
    assert all(parts), token  # rmw_zenoh rejects a token with an empty part
    return parts


def test_graph_names_per_mode():
    g = Graph("rmw_zenoh", 3, "abc123", "racecav", namespace="car0")
    assert g.data_key("/scan", msgs.LASER_SCAN) == f"3/scan/sensor_msgs::msg::dds_::LaserScan_/{LASER_SCAN_HASH}"
    assert g.data_key("scan", msgs.LASER_SCAN).startswith("3/car0/scan/")  # relative: under the namespace
    assert _token_parts(g.node_token()) == ["@ros2_lv", "3", "abc123", "0", "0", "NN", "%", "%car0", "racecav"]
    token, gid = g.entity_token("MP", "/scan", msgs.LASER_SCAN)
    p = _token_parts(token)
    # AdminSpace, DomainId, Zid, Nid, Id, EntityStr, Enclave, Namespace, NodeName,
    # TopicName, TopicType, TopicTypeHash, TopicQoS (rmw_zenoh's KeyexprIndex)
    assert len(p) == 13 and p[5] == "MP" and p[3] == "0" and p[4] == "1"
    assert p[9:12] == ["%scan", "sensor_msgs::msg::dds_::LaserScan_", LASER_SCAN_HASH]
    assert len(gid) == 16
    t2, gid2 = g.entity_token("MS", "/drive", msgs.ACKERMANN_STAMPED)
    assert _token_parts(t2)[4] == "2" and gid2 != gid

    h = Graph("humble", 0, "z", "racecav")
    assert h.data_key("/scan", msgs.LASER_SCAN).endswith("/TypeHashNotSupported")
    assert len(h.entity_token("MP", "/scan", msgs.LASER_SCAN)[1]) == 16
    b = Graph("bridge", 0, "z", "racecav", bridge_prefix="car0")
    assert b.data_key("/scan", msgs.LASER_SCAN) == "car0/scan"
    assert b.node_token() is None and b.entity_token("MP", "/scan", msgs.LASER_SCAN) == (None, b"")


def _scan(seq: int, stamp: int) -> Scan:
    rng = np.random.default_rng(seq)
    ranges = rng.uniform(0.2, 11.0, 170).astype(np.float32)
    ranges[5] = np.inf  # no return stays +inf in the LaserScan
    return Scan(stamp_ns=stamp, seq=seq, source="sim", angle_min=-math.pi / 4, angle_max=math.pi / 4,
                angle_increment=math.pi / 2 / 169, range_min=0.1, range_max=12.0, scan_time=0.1, ranges=ranges)


class Capture:
    """Every sample under a key expression: (key, payload, attachment or None)."""

    def __init__(self, session, key: str):
        self.items: list[tuple[str, bytes, bytes | None]] = []
        self._sub = session.declare_subscriber(key, self._on)

    def _on(self, s) -> None:
        self.items.append((str(s.key_expr), s.payload.to_bytes(),
                           s.attachment.to_bytes() if s.attachment is not None else None))

    def on(self, key: str):
        return [i for i in self.items if i[0] == key]

    def close(self):
        self._sub.undeclare()


def _wait(pred, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(0.05)
    raise TimeoutError(what)


def _ready(session) -> dict:
    """The mirror's status once its setup is done (its liveliness token comes a moment before)."""
    deadline = time.monotonic() + 10
    while True:
        info = get_status(session, "car0", "ros2").info
        if len(info["keys"]) == 4 or time.monotonic() > deadline:
            return info
        time.sleep(0.05)


@pytest.mark.parametrize("mode", ["rmw_zenoh", "humble", "bridge", "second-router"])
def test_mirror_modes_and_drive_input(mode, spawn, session, router, bus_cfg, tmp_path):
    """A Scan in -> a LaserScan on the mode's key (and a ROS /drive -> a DriveCommand), for each
    mode; "second-router": the ROS side is its own Zenoh network (an rmw_zenohd stand-in)."""
    # header stamps: the racecav stamp ("source"), or the arrival wall clock (the default; bridge case)
    env = {} if mode == "bridge" else {"RACECAV_ROS2__STAMPS": "source"}
    ros_session, ros_router = session, None
    if mode == "second-router":
        from racecav.common.client import open_session

        ros_router = procs.router(log_path=tmp_path / "ros-router.log")
        ros_ep = ros_router.__enter__()
        env["RACECAV_ROS2__CONNECT"] = f'["{ros_ep}"]'
        ros_bus = bus_cfg.bus.model_copy(update={"connect": [ros_ep]})
        ros_session = open_session(bus_cfg.model_copy(update={"bus": ros_bus}))
    else:
        env["RACECAV_ROS2__MODE"] = mode
    try:
        cap = Capture(ros_session, "**")
        drive_cmds: list[DriveCommand] = []
        sub = session.declare_subscriber(keys.topic("car0", keys.DRIVE_ROS),
                                         lambda s: drive_cmds.append(decode(s.payload.to_bytes(), DriveCommand)))
        proc = spawn("ros2", env=env)
        procs.wait_alive(session, "car0", "ros2", proc=proc)
        info = _ready(session)
        scan_key, drive_key = info["keys"]["/scan"], info["keys"]["/drive"]
        rmw = mode != "bridge"
        hash_slot = {"rmw_zenoh": LASER_SCAN_HASH, "second-router": LASER_SCAN_HASH,
                     "humble": "TypeHashNotSupported"}.get(mode)
        assert scan_key == (f"0/scan/sensor_msgs::msg::dds_::LaserScan_/{hash_slot}" if rmw else "scan")

        # the graph: a node token and one token per publisher / subscription (rmw modes only)
        tokens = [str(r.ok.key_expr) for r in ros_session.liveliness().get("@ros2_lv/**", timeout=1.0) if r.ok]
        if rmw:
            assert sum(t.split("/")[5] == "NN" and t.endswith("/racecav") for t in tokens) == 1, tokens
            mp = {t.split("/")[9]: t.split("/") for t in tokens if t.split("/")[5] == "MP"}
            assert set(mp) == {"%scan", "%odom", "%drive_out"}
            assert mp["%scan"][10:12] == ["sensor_msgs::msg::dds_::LaserScan_", hash_slot]
            assert [t for t in tokens if t.split("/")[5] == "MS"][0].split("/")[9] == "%drive"
        else:
            assert tokens == []

        scans = [_scan(i, 1_000_000_000 * (i + 1) + 7) for i in range(3)]
        for s in scans:
            session.put(keys.topic("car0", keys.SCAN), encode(s))
        _wait(lambda: len(cap.on(scan_key)) >= 3, 5, "no LaserScan mirrored")
        for (_k, payload, att), s in zip(cap.on(scan_key), scans):
            ls = idl.LaserScan.deserialize(payload)
            assert payload[:4] == b"\x00\x01\x00\x00"  # CDR little-endian encapsulation
            if mode == "bridge":
                assert abs(idl.stamp_ns(ls.header) - time.time_ns()) < 5e9 and ls.header.frame_id == "laser"
            else:
                assert idl.stamp_ns(ls.header) == s.stamp_ns and ls.header.frame_id == "laser"
            assert np.array_equal(np.asarray(ls.ranges, np.float32), s.ranges)
            assert ls.angle_min == pytest.approx(s.angle_min, abs=1e-7) and len(ls.intensities) == 0
            if rmw:
                seq, ts, gid = parse_attachment(att)
                assert len(att) == 33
                assert abs(ts - time.time_ns()) < 5e9 and len(gid) == 16
            else:
                assert att is None
        if rmw:
            assert [parse_attachment(a)[0] for _k, _p, a in cap.on(scan_key)] == [1, 2, 3]

        # ROS /drive -> DriveCommand on drive_ros (source "ros"), garbage counted and dropped
        car = load_car("slash")
        ros_session.put(drive_key, b"\x00\x01\x00\x00garbage")
        kw = {"attachment": attachment(1, time.time_ns(), bytes(16))} if rmw else {}
        ros_session.put(drive_key, idl.drive_cdr(0.12, 1.5), **kw)
        _wait(lambda: drive_cmds, 5, "no DriveCommand from /drive")
        c = drive_cmds[0]
        assert c.source == "ros" and c.steering_angle == pytest.approx(0.12, abs=1e-6)
        assert steady_speed(c.throttle, car, car.agent_speed_scale) == pytest.approx(1.5, rel=1e-4)
        st = get_status(session, "car0", "ros2")
        assert st.invalid == 1 and st.info["messages"]["/drive"] == 1
        assert proc.poll() is None
        sub.undeclare()
        cap.close()
    finally:
        if ros_router is not None:
            ros_session.close()
            ros_router.__exit__(None, None, None)


def test_sim_policy_mirror_end_to_end(spawn, session, tmp_path):
    """`racecav sim` + `racecav policy` + `racecav ros2`: every mirrored LaserScan, Odometry and
    AckermannDriveStamped decodes (pycdr2) to the racecav message with the same stamp."""
    car = load_car("slash")
    got = {k: [] for k in (keys.SCAN, keys.STATE, keys.CMD)}
    cls = {keys.SCAN: Scan, keys.STATE: VehicleState, keys.CMD: DriveCommand}
    subs = [session.declare_subscriber(keys.topic("car0", k),
                                       lambda s, k=k: got[k].append(decode(s.payload.to_bytes(), cls[k])))
            for k in got]
    cap = Capture(session, "0/**")
    ros = spawn("ros2", env={"RACECAV_ROS2__STAMPS": "source"})
    procs.wait_alive(session, "car0", "ros2", proc=ros)
    _ready(session)
    sim = spawn("sim", "--mode", "lockstep")
    procs.wait_alive(session, "car0", "sim", proc=sim)
    pol = spawn("policy")
    _wait(lambda: len(got[keys.CMD]) >= 20, 60, "the policy did not drive 20 steps")
    procs.stop(pol)
    procs.stop(sim)
    time.sleep(0.3)
    for s in subs:
        s.undeclare()
    cap.close()

    by_key: dict[str, list] = {}
    for k, payload, att in cap.items:
        assert att is not None and len(att) == 33
        by_key.setdefault(k.split("/")[1], []).append(payload)
    assert set(by_key) == {"scan", "odom", "drive_out"}
    assert {k for k, _p, _a in cap.items} == {
        f"0/scan/sensor_msgs::msg::dds_::LaserScan_/{LASER_SCAN_HASH}",
        f"0/odom/nav_msgs::msg::dds_::Odometry_/{msgs.type_hash(msgs.ODOMETRY)}",
        f"0/drive_out/ackermann_msgs::msg::dds_::AckermannDriveStamped_/{ACKERMANN_STAMPED_HASH}"}

    scans = {s.stamp_ns: s for s in got[keys.SCAN]}
    for payload in by_key["scan"]:
        ls = idl.LaserScan.deserialize(payload)
        s = scans[idl.stamp_ns(ls.header)]
        assert np.array_equal(np.asarray(ls.ranges, np.float32), s.ranges)
        assert (ls.range_min, ls.range_max) == pytest.approx((s.range_min, s.range_max))
    states = {s.stamp_ns: s for s in got[keys.STATE]}
    for payload in by_key["odom"]:
        od = idl.Odometry.deserialize(payload)
        s = states[idl.stamp_ns(od.header)]
        p, q = od.pose.pose.position, od.pose.pose.orientation
        assert (p.x, p.y, od.twist.twist.linear.x, od.twist.twist.angular.z) == (s.x, s.y, s.vx, s.yaw_rate)
        assert 2 * math.atan2(q.z, q.w) == pytest.approx(s.yaw, abs=1e-9)
        assert od.header.frame_id == "odom" and od.child_frame_id == "base_link"
    cmds = {c.stamp_ns: c for c in got[keys.CMD]}
    assert len(by_key["drive_out"]) >= 20
    for payload in by_key["drive_out"]:
        ad = idl.AckermannDriveStamped.deserialize(payload)
        c = cmds[idl.stamp_ns(ad.header)]
        assert ad.drive.steering_angle == pytest.approx(c.steering_angle, abs=1e-6)
        assert ad.drive.speed == pytest.approx(steady_speed(c.throttle, car, car.agent_speed_scale), abs=1e-5)


def test_ros_drive_drives_the_sim(spawn, session):
    """ROS /drive -> racecav ros2 -> drive_ros -> the sim's mux: with no controller running, the
    AckermannDriveStamped commands drive the simulated car (F1TENTH's /drive convention)."""
    ros = spawn("ros2")
    procs.wait_alive(session, "car0", "ros2", proc=ros)
    _ready(session)
    # realtime, clock running from the start (its wait for a first command watches the
    # controller key only)
    sim = spawn("sim", "--mode", "realtime", env={"RACECAV_SIM__WAIT_FOR_CONTROLLER": "false"})
    procs.wait_alive(session, "car0", "sim", proc=sim)
    states: list[VehicleState] = []
    sub = session.declare_subscriber(keys.topic("car0", keys.STATE),
                                     lambda s: states.append(decode(s.payload.to_bytes(), VehicleState)))
    key = f"0/drive/ackermann_msgs::msg::dds_::AckermannDriveStamped_/{ACKERMANN_STAMPED_HASH}"
    pub = session.declare_publisher(key)
    for i in range(30):  # 1.5 s at 20 Hz, steering left
        pub.put(idl.drive_cdr(0.25, 1.5), attachment=attachment(i + 1, time.time_ns(), bytes(16)))
        time.sleep(0.05)
    info = get_status(session, "car0", "sim").info
    pub.undeclare()
    sub.undeclare()
    brief = {k: info.get(k) for k in ("mux", "started", "episode", "done", "last_source")}
    assert info["last_source"] == "ros" and info["mux"]["accepted_by"].get("ros", 0) > 0, brief
    assert states and max(s.steering_angle for s in states) > 0.1  # the car steers left as asked
