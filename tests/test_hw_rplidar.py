"""RPLIDAR S2: protocol vectors, dense decoding, and the real driver against the emulator on a pty."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from racecav.common.lidar import LidarSpec, ray_angles
from racecav.services.sensor import rplidar_protocol as rp
from racecav.services.sensor.emulator import EXPRESS_MODE, S2_MODES, RplidarEmulator, WallScene, default_walls
from racecav.services.sensor.preprocess import PreprocessParams, cut_angle_deg, preprocess, revolution_to_scan
from racecav.services.sensor.rplidar_driver import RplidarDriver

H = bytes.fromhex


# --- byte-exact vectors (shared/reference/hardware-protocols.md) ------------------------------

def test_request_vectors():
    assert rp.motor_speed_request(0) == H("A5 A8 02 00 00 0F")
    assert rp.motor_speed_request(600) == H("A5 A8 02 58 02 55")
    assert rp.express_scan_request(0) == H("A5 82 05 00 00 00 00 00 22")
    assert rp.express_scan_request(1) == H("A5 82 05 01 00 00 00 00 23")
    assert rp.conf_request(rp.CONF_SCAN_MODE_COUNT) == H("A5 84 04 70 00 00 00 55")
    assert rp.conf_request(rp.CONF_SCAN_MODE_ANS_TYPE, 1) == H("A5 84 06 75 00 00 00 01 00 53")
    assert rp.conf_request(rp.CONF_SCAN_MODE_TYPICAL) == H("A5 84 04 7C 00 00 00 59")
    assert rp.request(rp.CMD_STOP) == H("A5 25") and rp.request(rp.CMD_RESET) == H("A5 40")


@pytest.mark.parametrize("desc,hexs", [
    (rp.Descriptor(0x14, 0, rp.ANS_INFO), "A5 5A 14 00 00 00 04"),
    (rp.Descriptor(3, 0, rp.ANS_HEALTH), "A5 5A 03 00 00 00 06"),
    (rp.Descriptor(5, 1, rp.ANS_STANDARD), "A5 5A 05 00 00 40 81"),
    (rp.Descriptor(0x54, 1, rp.ANS_EXPRESS), "A5 5A 54 00 00 40 82"),
    (rp.Descriptor(0x84, 1, rp.ANS_ULTRA), "A5 5A 84 00 00 40 84"),
    (rp.Descriptor(0x54, 1, rp.ANS_DENSE), "A5 5A 54 00 00 40 85"),
])
def test_descriptor_vectors(desc, hexs):
    assert desc.encode() == H(hexs)
    assert rp.Descriptor.parse(H(hexs)) == desc


def test_request_parser_checks_checksums():
    p = rp.RequestParser()
    bad = bytearray(rp.motor_speed_request(600))
    bad[-1] ^= 1
    reqs = p.feed(b"\x00\x17" + rp.request(rp.CMD_GET_INFO) + bytes(bad) + rp.conf_request(0x75, 1))
    assert [(r.cmd, r.payload) for r in reqs] == [(0x50, b""), (0x84, H("75 00 00 00 01 00"))]
    assert p.errors >= 2


# --- decoding ---------------------------------------------------------------------------------

def test_dense_capsule_layout_and_interpolation_across_zero():
    d0 = np.arange(40) * 10 + 500
    c0 = rp.encode_dense_capsule(358.0, d0)
    c1 = rp.encode_dense_capsule(2.5, np.full(40, 900))
    assert len(c0) == rp.CAPSULE_LEN and c0[0] >> 4 == 0xA and c0[1] >> 4 == 0x5
    assert rp.capsule_checksum_ok(c0) and rp.capsule_start(c0) == (358.0, False)
    assert np.frombuffer(c0[4:], "<u2").tolist() == d0.tolist()  # little-endian whole mm
    s = rp.ScanStream(rp.ANS_DENSE)
    assert len(s.feed(c0).angle_deg) == 0  # decoded only once the next capsule arrives
    out = s.feed(c1)
    want = np.mod(358.0 + 4.5 * np.arange(40) / 40, 360.0)  # difference taken modulo 360
    np.testing.assert_allclose(out.angle_deg, want, atol=1e-9)
    np.testing.assert_array_equal(out.dist_mm, d0)
    assert out.start.sum() == 1 and out.angle_deg[out.start][0] < 1.0  # wrapped past 0


def test_first_capsule_of_a_scan_is_not_paired_with_older_data():
    s = rp.ScanStream(rp.ANS_DENSE)
    s.feed(rp.encode_dense_capsule(100.0, np.full(40, 1)) + rp.encode_dense_capsule(104.5, np.full(40, 2)))
    out = s.feed(rp.encode_dense_capsule(10.0, np.full(40, 3), new_scan=True)
                 + rp.encode_dense_capsule(14.5, np.full(40, 4)))
    assert out.dist_mm.tolist() == [3] * 40


def test_express_capsule_round_trip():
    d = np.arange(32) * 4 + 1000
    off = np.arange(32) % 64
    c0 = rp.encode_express_capsule(90.0, d, off)
    c1 = rp.encode_express_capsule(93.0, d)
    out = rp.ScanStream(rp.ANS_EXPRESS).feed(c0 + c1)
    np.testing.assert_array_equal(out.dist_mm, d)
    np.testing.assert_allclose(out.angle_deg, 90.0 + 3.0 * np.arange(32) / 32 - off / 8.0)


def test_standard_nodes_resync_after_garbage_and_lost_byte():
    nodes = [rp.encode_standard_node(a, 1000 + a, start=(a == 0)) for a in range(0, 360, 3)]
    stream = b"".join(nodes[:10]) + H("FF 00 13") + b"".join(nodes[10:20]) + nodes[20][1:] + b"".join(nodes[21:])
    s = rp.ScanStream(rp.ANS_STANDARD)
    out = s.feed(stream[:333])
    out2 = s.feed(stream[333:])
    angles = np.concatenate([out.angle_deg, out2.angle_deg])
    dists = np.concatenate([out.dist_mm, out2.dist_mm])
    np.testing.assert_allclose(dists - angles, 1000.0, atol=0.25)  # every node decoded is right
    assert len(angles) >= len(nodes) - 3 and s.stats.bad_nodes > 0


def _dense_stream(scene, n_caps, spr=3200, first=0):
    caps = []
    for k in range(first, first + n_caps):
        q0 = round((k * 40 % spr) * 360 * 64 / spr) % (360 * 64)
        q1 = round(((k + 1) * 40 % spr) * 360 * 64 / spr) % (360 * 64)
        a = q0 / 64 + ((q1 - q0) % (360 * 64)) / 64 * np.arange(40) / 40
        caps.append(rp.encode_dense_capsule(q0 / 64, scene.ranges_mm(np.mod(a, 360.0)), new_scan=(k == 0)))
    return caps


def _matches_scene(scene, angle_deg, dist_mm, tol_mm=1.0):
    """Fraction of samples whose distance is what the scene has at the decoded angle."""
    truth = scene.ranges_mm(np.asarray(angle_deg))
    return float(np.mean(np.abs(truth - dist_mm) <= tol_mm))


def test_stream_recovers_from_checksum_garbage_and_truncation():
    scene = WallScene(default_walls())
    caps = _dense_stream(scene, 400)
    rng = np.random.default_rng(1)
    bad = bytearray(caps[50])
    bad[40] ^= 0x21  # checksum failure
    caps[50] = bytes(bad)
    caps[120] = caps[120][:37]  # truncated capsule
    caps[200] = rng.integers(0, 256, 300, dtype=np.uint8).tobytes() + caps[200]  # garbage
    data = b"".join(caps)
    s = rp.ScanStream(rp.ANS_DENSE)
    outs = [s.feed(data[i:i + 997]) for i in range(0, len(data), 997)]  # arbitrary read sizes
    a = np.concatenate([o.angle_deg for o in outs])
    d = np.concatenate([o.dist_mm for o in outs])
    assert s.stats.checksum >= 2 and s.stats.resync_bytes >= 300
    assert s.stats.capsules >= 396
    assert len(a) >= (396 - 6) * 40  # only the pairs touching a damaged capsule are lost
    assert _matches_scene(scene, a, d) > 0.998  # and nothing wrong got through


def test_revolutions_cut_where_asked():
    scene = WallScene(default_walls())
    s = rp.ScanStream(rp.ANS_DENSE)
    cut = 48.0
    asm = rp.RevolutionAssembler(cut)
    revs = asm.add(s.feed(b"".join(_dense_stream(scene, 80 * 4))))
    assert len(revs) == 3  # 4 turns from 0 deg: the partial turns before 48 and after the last cut are not whole
    for r in revs:
        assert len(r.angle_deg) == 3200
        assert abs(((r.angle_deg[0] - cut + 180) % 360) - 180) < 4.5


# --- preprocessing ----------------------------------------------------------------------------

def _rev_from_scene(scene, spr=3200):
    a = np.arange(spr) * 360.0 / spr
    return a, scene.ranges_mm(a)


def test_preprocess_matches_scene_at_ray_angles():
    spec = LidarSpec()
    scene = WallScene(default_walls())
    a, d = _rev_from_scene(scene)
    out = preprocess(a, d, spec)
    truth = scene.ranges_mm(-np.degrees(ray_angles(spec).astype(np.float64))) / 1000.0
    assert out.shape == (170,) and out.dtype == np.float32
    err = np.abs(out - truth)
    assert np.median(err) < 0.002 and np.mean(err < 0.01) > 0.97  # larger only at the box's edges


def test_preprocess_replaces_outliers_by_interpolation():
    spec = LidarSpec()
    a = np.arange(3200) * 360.0 / 3200
    d = np.full(3200, 2000.0)
    ahead = np.argmin(np.abs(a - 10.0))  # 10 deg to the right
    d[ahead] = 0.0  # no return
    d[ahead + 7] = np.nan
    d[ahead + 15] = 60000.0  # beyond range_max
    d[ahead + 22] = 400.0  # isolated spike
    d[ahead + 30:ahead + 32] = 10.0  # below range_min
    out = preprocess(a, d, spec)
    np.testing.assert_allclose(out, 2.0, atol=1e-5)


def test_preprocess_keeps_real_objects_and_long_holes():
    spec = LidarSpec()
    a = np.arange(3200) * 360.0 / 3200
    d = np.full(3200, 3000.0)
    d[(a > 350) | (a < 5)] = 800.0  # a 15 deg wide object just left of centre: not a spike
    d[(a > 20) & (a < 40)] = 0.0  # 20 deg of no return: an opening, not an outlier
    out = preprocess(a, d, spec, params=PreprocessParams(max_gap_deg=6.0))
    th = np.degrees(ray_angles(spec))
    assert np.all(out[(th > -4) & (th < 9)] == pytest.approx(0.8))
    assert np.all(np.isinf(out[(th < -22) & (th > -38)]))  # right side (device CW)


def test_mount_yaw_rotates_the_scan():
    spec = LidarSpec()
    a = np.arange(3200) * 360.0 / 3200
    d = np.where(np.abs(((a - 90) + 180) % 360 - 180) < 10, 1000.0, 4000.0)  # object at device 90 deg
    # The device's 0 mark points left (+90 deg): its 90 deg (clockwise) is straight ahead.
    out = preprocess(a, d, spec, mount_yaw=math.pi / 2)
    assert out[85] == pytest.approx(1.0) and out[0] == pytest.approx(4.0)
    assert cut_angle_deg(spec, 0.0) == pytest.approx(48.0)


def test_revolution_to_scan_is_a_valid_real_scan():
    spec = LidarSpec()
    a, d = _rev_from_scene(WallScene(default_walls()))
    k = int(np.searchsorted(a, cut_angle_deg(spec)))  # a revolution as the driver cuts it
    a, d = np.roll(a, -k), np.roll(d, -k)
    scan = revolution_to_scan(a, d, 5_000_000_000, 31.25, 7, spec)
    assert scan.source == "real" and scan.seq == 7 and len(scan.ranges) == 170
    assert scan.angle_min == pytest.approx(-math.pi / 4) and scan.time_increment < 0
    # ranges[0] (rightmost) is measured last, just before the cut: stamped a few ms before the end.
    assert 4_990_000_000 < scan.stamp_ns < 5_000_000_000 and scan.scan_time == pytest.approx(0.1)


# --- the driver against the emulator on a pty -------------------------------------------------

FAST = dict(reset_wait_s=0.15, spinup_s=0.05, data_timeout_s=0.4, reconnect_s=0.1, reply_timeout_s=0.5)


class Run:
    """Emulator + driver thread; collects revolutions."""

    def __init__(self, tmp_path, scan_mode=None, scene=None, **emu_kw):
        self.emu = RplidarEmulator(scene, link=tmp_path / "rplidar", reset_s=0.1, **emu_kw).start()
        self.revs: list[rp.Revolution] = []
        self.drv = RplidarDriver(self.emu.path, self.revs.append, scan_mode=scan_mode, **FAST)
        self.thread = self.drv.start_thread()

    def wait_revs(self, n, timeout=6.0):
        deadline = time.monotonic() + timeout
        while len(self.revs) < n and time.monotonic() < deadline:
            time.sleep(0.02)
        assert len(self.revs) >= n, f"{len(self.revs)} revolutions, driver {self.drv.status()}"

    def close(self):
        self.drv.stop_event.set()
        self.thread.join(3)
        self.emu.stop()
        assert not self.thread.is_alive()


@pytest.fixture
def lidar(tmp_path):
    runs = []

    def make(**kw):
        runs.append(Run(tmp_path, **kw))
        return runs[-1]

    yield make
    for r in runs:
        r.close()


def test_handshake_over_pty(lidar):
    run = lidar()
    run.wait_revs(2)
    drv, emu = run.drv, run.emu
    assert drv.info.model_major == 7 and drv.info.serial == "C0FFEE00112233445566778899AABBCC"
    assert drv.health == rp.Health(0, 0)
    assert (drv.mode_count, drv.typical_mode, drv.mode, drv.mode_name) == (2, 1, 1, "DenseBoost")
    assert drv.answer_type == rp.ANS_DENSE and drv.us_per_sample == pytest.approx(31.25)
    sent = [rp.request(c, p) if c >= 0x80 else rp.request(c) for _, c, p in emu.requests]
    expected = [rp.request(rp.CMD_STOP), rp.request(rp.CMD_RESET), rp.request(rp.CMD_GET_INFO),
                rp.request(rp.CMD_GET_HEALTH), rp.conf_request(0x70), rp.conf_request(0x7C),
                rp.conf_request(0x75, 1), rp.conf_request(0x71, 1), rp.conf_request(0x7F, 1),
                rp.motor_speed_request(600), rp.express_scan_request(1)]
    assert sent[:len(expected)] == expected
    assert emu.rpm == 600 and emu.streaming


def test_dense_revolutions_over_pty_match_the_scene_and_pace(lidar):
    run = lidar()
    run.wait_revs(1)
    t0, n0 = time.monotonic(), len(run.revs)
    run.wait_revs(n0 + 5)
    rate = (len(run.revs) - n0) / (time.monotonic() - t0)
    assert 7.0 < rate < 13.0  # paced like the device: 10 revolutions per second, not a flood
    for r in run.revs[-3:]:
        assert len(r.angle_deg) == 3200
        assert _matches_scene(run.emu.scene, r.angle_deg, r.dist_mm) > 0.998
    assert run.drv.stats.parser.errors() == 0


@pytest.mark.parametrize("mode,atype", [(0, rp.ANS_STANDARD), (2, rp.ANS_EXPRESS)])
def test_other_scan_modes_over_pty(lidar, mode, atype):
    run = lidar(scan_mode=mode, modes=S2_MODES + (EXPRESS_MODE,))
    run.wait_revs(2)
    assert run.drv.answer_type == atype
    r = run.revs[-1]
    assert _matches_scene(run.emu.scene, r.angle_deg, r.dist_mm, tol_mm=1.0) > 0.99


def test_faults_over_pty_are_counted_and_recovered(lidar):
    run = lidar()
    run.wait_revs(1)
    emu = run.emu
    emu.corrupt_next(3)
    emu.inject_garbage(500)
    time.sleep(0.15)
    emu.truncate_next(2)
    n = len(run.revs)
    run.wait_revs(n + 4)
    st = run.drv.stats.parser
    assert st.checksum >= 3 and st.resync_bytes >= 500
    assert run.drv.stats.restarts == 0 and run.drv.stats.connects == 1
    for r in run.revs[-4:]:
        assert _matches_scene(emu.scene, r.angle_deg, r.dist_mm) > 0.998
    assert len(run.revs[-1].angle_deg) == 3200  # later revolutions are whole again


def test_unplug_and_replug(lidar):
    run = lidar()
    run.wait_revs(1)
    run.emu.unplug(0.6)
    time.sleep(0.3)
    assert run.drv.stats.disconnects == 1 and run.drv.state in ("waiting for device", "disconnected")
    n = len(run.revs)
    run.wait_revs(n + 2, timeout=8)
    assert run.drv.stats.connects == 2 and run.emu.plug_count == 2 and run.thread.is_alive()


def test_health_error_resets_and_restarts(lidar):
    run = lidar()
    run.wait_revs(1)
    run.emu.set_health(rp.HEALTH_ERROR, 0x8003)
    deadline = time.monotonic() + 5
    while run.drv.stats.restarts == 0 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert run.drv.stats.restarts == 1 and "0x8003" in run.drv.stats.last_error
    n = len(run.revs)
    run.wait_revs(n + 2)
    assert run.drv.health.status == rp.HEALTH_OK


def test_replayed_scan_comes_back_through_the_real_pipeline(lidar, tmp_path):
    """A simulator-style scan replayed by the emulator, read by the driver and preprocessed,
    gives back the same 170 ranges: the real path adds no distortion of its own."""
    from racecav.services.sensor.emulator import ReplayScene
    from racecav.services.sensor.record_scans import save_replay
    from racecav.common.lidar import make_scan

    spec = LidarSpec()
    rng = np.random.default_rng(3)
    rays = 2.0 + np.cumsum(rng.normal(0, 0.05, 170)).astype(np.float32)  # a wiggly wall, 1-4 m
    rays[100:120] = np.inf  # an opening (10.6 deg: wider than max_gap_deg, so not interpolated)
    save_replay(tmp_path / "scans.npz", [make_scan(rays, 0, 0, "sim", spec)])
    run = lidar(scene=ReplayScene(tmp_path / "scans.npz"))
    run.wait_revs(2)
    r = run.revs[-1]
    out = preprocess(r.angle_deg, r.dist_mm, spec)
    finite = np.isfinite(rays)
    np.testing.assert_allclose(out[finite], rays[finite], atol=0.0011)  # whole-mm distances
    assert np.all(np.isinf(out[101:119]))


# Five consecutive express capsules (82) captured from a real RPLIDAR, and the SDK's decoding
# of them (angle_z_q14, dist_mm_q2 per sample), from pyrplidar's tests (Hyun-je/pyrplidar,
# test/test_pyrplidar_protocol.py): regression vectors recorded on hardware.
REAL_EXPRESS_CAPSULES = [
    'ac5012517e097209de66095a09ce66096e09cd62096209ec5e095a09dd4e095a09dc62095609cd56094e09dc3e093a09dd3a093a09cd36093609cc36093609de36093a09dc3a094209cd4e094a09ec56096a09dd',
    'ae5adb546a097209ee76096a09dd66096209ce5a095a09cd5e096e09ec7a097e09ee82098a09dd8e099a09dea209ae09eeb209ae09eeb209b609eeba09be09fec609ca09fed209d209efd609de09dfea09f609ee',
    'ae5b8f58f609060afe1e0a260aff2e0a320aff320a360aff3a0a420aee4e0a560aef5e0a6a0aff7a0a830a0f930a9e0af09e0aa20affa70aa60af09e0a9a0aff970a960af09b0aa30a00af0ab70a00c20acf0a0f',
    'af584302d70adf0a00f20af70a0fe30ae60af0e60af30a0f02008a0aff660a670a0f660a620aff620a0200ffea09260aff00000000000300ef0a00f30af70a01ff0a070b01170b2b0b00470b670b10830bbb0b21',
    'ab51f70500000000000300d70d33030e130e44fb0dc70d337b0d030033c70c8f0c23730c670c225b0c5b0c21630c6b0c21770c8b0c22b30cd30c33ef0c170d32530d030044270e4b0e44530e5b0e445f0e6b0e44',
]
REAL_EXPRESS_SDK_ANGLE_Q14 = [
    0xe282, 0xe2ee, 0xe32d, 0xe3b0, 0xe3f1, 0xe45d, 0xe4b3, 0xe4db, 0xe549, 0xe59f, 0xe60b, 0xe64c, 0xe6a2, 0xe70e, 0xe763, 0xe7a4,
    0xe7fa, 0xe84f, 0xe8a7, 0xe913, 0xe969, 0xe9be, 0xe9e9, 0xea55, 0xeac1, 0xeb02, 0xeb58, 0xebc4, 0xec19, 0xec44, 0xecb0, 0xed05,
    0xed47, 0xed99, 0xee05, 0xee58, 0xee96, 0xef19, 0xef55, 0xefc1, 0xf016, 0xf03b, 0xf091, 0xf0e3, 0xf14f, 0xf1a4, 0xf1e0, 0xf24c,
    0xf28b, 0xf2dd, 0xf333, 0xf385, 0xf3db, 0xf430, 0xf482, 0xf4c1, 0xf52d, 0xf569, 0xf5be, 0xf627, 0xf666, 0xf6e9, 0xf724, 0xf77a,
    0xf7cf, 0xf80b, 0xf860, 0xf8b3, 0xf908, 0xf95d, 0xf9b0, 0xfa05, 0xfa71, 0xfac4, 0xfb02, 0xfb6c, 0xfbaa, 0xfc00, 0xfc52, 0xfc91,
    0xfce6, 0xfd4f, 0xfda4, 0xfdf7, 0xfe36, 0xfea2, 0xfef4, 0xff49, 0xff88, 0xfff1, 0x30, 0x82, 0xd8, 0x12d, 0x196, 0x1d5,
    0x22a, 0x27d, 0x2e9, 0x324, 0x37a, 0x3e6, 0x438, 0x477, 0x4e3, 0x536, 0x58b, 0x5c7, 0x633, 0x688, 0x6db, 0x730,
    0x785, 0x7d8, 0xc5b, 0xcad, 0x8be, 0x913, 0x94f, 0x9bb, 0x9fa, 0xa63, 0xab8, 0xb0b, 0xb60, 0xb9f, 0xbf1, 0xc30,
]
REAL_EXPRESS_SDK_DIST_Q2 = [
    0x97c, 0x970, 0x964, 0x958, 0x964, 0x96c, 0x960, 0x960, 0x95c, 0x958, 0x94c, 0x958, 0x960, 0x954, 0x954, 0x94c,
    0x93c, 0x938, 0x938, 0x938, 0x934, 0x934, 0x934, 0x934, 0x934, 0x938, 0x938, 0x940, 0x94c, 0x948, 0x954, 0x968,
    0x968, 0x970, 0x974, 0x968, 0x964, 0x960, 0x958, 0x958, 0x95c, 0x96c, 0x978, 0x97c, 0x980, 0x988, 0x98c, 0x998,
    0x9a0, 0x9ac, 0x9b0, 0x9ac, 0x9b0, 0x9b4, 0x9b8, 0x9bc, 0x9c4, 0x9c8, 0x9d0, 0x9d0, 0x9d4, 0x9dc, 0x9e8, 0x9f4,
    0x9f4, 0xa04, 0xa1c, 0xa24, 0xa2c, 0xa30, 0xa30, 0xa34, 0xa38, 0xa40, 0xa4c, 0xa54, 0xa5c, 0xa68, 0xa78, 0xa80,
    0xa90, 0xa9c, 0xa9c, 0xaa0, 0xaa4, 0xaa4, 0xa9c, 0xa98, 0xa94, 0xa94, 0xa98, 0xaa0, 0xaac, 0xab4, 0xac0, 0xacc,
    0xad4, 0xadc, 0xaf0, 0xaf4, 0xae0, 0xae4, 0xae4, 0xaf0, 0x0, 0xa88, 0xa64, 0xa64, 0xa64, 0xa60, 0xa60, 0x0,
    0x9e8, 0xa24, 0x0, 0x0, 0x0, 0xaec, 0xaf0, 0xaf4, 0xafc, 0xb04, 0xb14, 0xb28, 0xb44, 0xb64, 0xb80, 0xbb8,
]


def test_real_express_capture_decodes_like_the_sdk():
    data = b"".join(bytes.fromhex(c) for c in REAL_EXPRESS_CAPSULES)
    assert all(rp.capsule_checksum_ok(bytes.fromhex(c)) for c in REAL_EXPRESS_CAPSULES)
    s = rp.ScanStream(rp.ANS_EXPRESS)
    out = s.feed(data)
    assert s.stats.errors() == 0 and len(out.angle_deg) == 4 * 32  # the last capsule awaits its successor
    dist = np.array(REAL_EXPRESS_SDK_DIST_Q2) / 4.0
    angle = np.array(REAL_EXPRESS_SDK_ANGLE_Q14) * 90.0 / 16384.0
    hit = dist > 0  # the SDK's angles of no-return samples are off-sequence (0xC5B amid 0x7D8..0x8BE): skip them
    np.testing.assert_array_equal(out.dist_mm, dist)
    err = (out.angle_deg[hit] - angle[hit] + 180.0) % 360.0 - 180.0
    assert np.abs(err).max() < 0.025  # the SDK's fixed-point rounding (q8 start angles, q14 output)


def test_emulator_streams_only_between_scan_and_stop(tmp_path):
    """The emulator as a device: descriptor, capsules with the start flag on the first only, evenly
    stepped start angles, paced output; nothing after A5 25."""
    import serial

    emu = RplidarEmulator(link=tmp_path / "rp").start()
    try:
        port = serial.Serial(emu.path, 1_000_000, timeout=0.3)
        port.write(rp.motor_speed_request(600) + rp.express_scan_request(1))
        assert rp.Descriptor.parse(port.read(7)) == rp.Descriptor(0x54, rp.MODE_MULTI, rp.ANS_DENSE)
        t0 = time.monotonic()
        data = port.read(84 * 80)  # one revolution's worth
        elapsed = time.monotonic() - t0
        caps = [data[i:i + 84] for i in range(0, len(data), 84)]
        assert len(caps) == 80 and all(rp.capsule_checksum_ok(c) for c in caps)
        starts = [rp.capsule_start(c) for c in caps]
        assert [flag for _, flag in starts] == [True] + [False] * 79
        steps = np.diff([a for a, _ in starts])
        np.testing.assert_allclose(steps, 4.5, atol=1 / 64)
        assert elapsed > 0.08  # 80 capsules take ~100 ms on the real link, not a burst
        port.write(rp.request(rp.CMD_STOP))
        time.sleep(0.05)
        port.reset_input_buffer()
        assert port.read(100) == b"" and not emu.streaming
        port.close()
    finally:
        emu.stop()
