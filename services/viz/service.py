"""``racecav viz``: the car's bus as a live Foxglove view (Foxglove SDK WebSocket server).

Open Foxglove, "Open connection" -> ``ws://HOST:8765`` (Foxglove WebSocket). Channels:

| topic        | schema                    | from                  | what                                     |
|--------------|---------------------------|-----------------------|------------------------------------------|
| /scan        | foxglove.LaserScan        | racecav/<car>/scan    | the scan in the ``laser`` frame          |
| /tf          | foxglove.FrameTransforms  | state + car file      | odom -> base_link (pose), base_link -> laser (mount) |
| /cars        | foxglove.SceneUpdate      | state + obstacles     | the ego and the obstacle cars as boxes in ``odom`` |
| /walls       | foxglove.SceneUpdate      | the world file        | wall segments as lines in ``odom`` (re-sent every 2 s) |
| /cmd         | JSON racecav.DriveCommand | racecav/<car>/cmd     | a_throttle, a_steer, throttle, steering_angle, source |
| /latency     | JSON racecav.Latency      | scan + cmd arrivals   | scan -> command ms on this host's clock, controller compute ms |

``--mcap PATH`` also writes every channel to an MCAP file (Foxglove opens it). Logging happens in
the subscriber callbacks: building and logging a 170-ray LaserScan took 6 us (median, no viewer
connected, on the reference machine), a transform 2 us.
"""

from __future__ import annotations

import argparse
import math
import threading
import time
from typing import Any

from racecav.common import keys
from racecav.common.bus import Service
from racecav.common.config import Config, apply_options
from racecav.common.messages import DriveCommand, ObstacleStates, Scan, VehicleState

EXAMPLES = """examples:
  racecav viz                              # then Foxglove: Open connection -> ws://127.0.0.1:8765
  racecav viz --host 0.0.0.0 --port 8765   # reachable from the laptop (the car's network)
  racecav viz --mcap view.mcap             # also write the channels to a file
  racecav viz --world racetrack            # walls of another world than the sim's scenario
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", help="listen address (default: viz.host = 127.0.0.1)")
    p.add_argument("--port", type=int, help="WebSocket port (default: viz.port = 8765; 0 = any free port)")
    p.add_argument("--mcap", help="also write the channels to this MCAP file")
    p.add_argument("--world", help="world whose walls to draw (default: the world of sim.scenario)")
    p.epilog = EXAMPLES
    p.formatter_class = argparse.RawDescriptionHelpFormatter


def _ts(ns: int):
    from foxglove.messages import Timestamp

    return Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def _json_schema(name: str, properties: dict):
    """A named JSON schema (a dict would get a generated name in the file and the viewer)."""
    import json

    import foxglove

    return foxglove.Schema(name=name, encoding="jsonschema",
                           data=json.dumps({"title": name, "type": "object", "properties": properties}).encode())


def _quat(yaw: float):
    from foxglove.messages import Quaternion

    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))


class Viz(Service):
    """The viewer's bus side. :param cfg: whole configuration (section ``viz``)."""

    def __init__(self, cfg: Config, host: str, port: int, mcap: str | None = None, world: str | None = None):
        super().__init__(cfg, "viz")
        try:
            import foxglove  # noqa: F401
        except ImportError as e:
            raise ImportError("racecav viz needs the viz extra: pip install 'racecav[viz]'") from e
        from racecav.common.vehicle import load_car

        self.host, self.port, self.mcap_path = host, port, mcap
        self.car_params = load_car(cfg.sim.car)
        self.world_name = world
        if world is None:
            try:
                from racecav.common.scenario import load_scenario

                self.world_name = load_scenario(cfg.sim.scenario).world
            except (ValueError, FileNotFoundError) as e:
                self.log.warning("no walls: %s", e)
        self.counts = {"scan": 0, "state": 0, "obstacles": 0, "cmd": 0}
        self._lock = threading.Lock()
        self._scan_arrival: dict[tuple[int, int], int] = {}
        self._last_walls = 0.0
        self.server = None
        self._mcap = None

    # ------------------------------------------------------------------ setup
    def setup(self) -> None:
        import foxglove
        from foxglove.channels import FrameTransformsChannel, LaserScanChannel, SceneUpdateChannel

        if self.mcap_path:
            self._mcap = foxglove.open_mcap(self.mcap_path, allow_overwrite=True)
        self.server = foxglove.start_server(name=f"racecav {self.car}", host=self.host, port=self.port)
        self.ch_scan = LaserScanChannel("/scan")
        self.ch_tf = FrameTransformsChannel("/tf")
        self.ch_cars = SceneUpdateChannel("/cars")
        self.ch_walls = SceneUpdateChannel("/walls")
        num = {"type": "number"}
        self.ch_cmd = foxglove.Channel("/cmd", message_encoding="json", schema=_json_schema(
            "racecav.DriveCommand", {"a_throttle": num, "a_steer": num, "throttle": num, "steering_angle": num,
                                     "source": {"type": "string"}, "scan_seq": num}))
        self.ch_latency = foxglove.Channel("/latency", message_encoding="json", schema=_json_schema(
            "racecav.Latency", {"scan_to_cmd_ms": num, "compute_ms": num}))
        self._walls = None
        if self.world_name:
            from racecav.common.world import load_world

            self._walls = load_world(self.world_name).walls
        self.subscribe(self.topic(keys.SCAN), Scan, self._on_scan)
        self.subscribe(self.topic(keys.STATE), VehicleState, self._on_state)
        self.subscribe(self.topic(keys.OBSTACLES), ObstacleStates, self._on_obstacles)
        self.subscribe(self.topic(keys.CMD), DriveCommand, self._on_cmd)
        self.log.info("Foxglove WebSocket server on ws://%s:%d", self.host, self.server.port)

    # ------------------------------------------------------------------ callbacks
    def _on_scan(self, scan: Scan) -> None:
        from foxglove.messages import LaserScan, Pose, Vector3

        now = time.time_ns()
        with self._lock:
            self._scan_arrival[(scan.seq, scan.stamp_ns)] = time.monotonic_ns()
            if len(self._scan_arrival) > 64:  # answered or not: keep the recent ones only
                self._scan_arrival.pop(next(iter(self._scan_arrival)))
        self.ch_scan.log(LaserScan(
            timestamp=_ts(now), frame_id=scan.frame_id,
            pose=Pose(position=Vector3(x=0.0, y=0.0, z=0.0), orientation=_quat(0.0)),
            start_angle=float(scan.angle_min), end_angle=float(scan.angle_max),
            ranges=scan.ranges.astype(float).tolist(), intensities=scan.intensities.astype(float).tolist()),
            log_time=now)
        self.counts["scan"] += 1

    def _on_state(self, st: VehicleState) -> None:
        from foxglove.messages import FrameTransform, FrameTransforms, SceneUpdate, Vector3

        now = time.time_ns()
        m = self.car_params.lidar_mount
        self.ch_tf.log(FrameTransforms(transforms=[
            FrameTransform(timestamp=_ts(now), parent_frame_id=st.frame_id, child_frame_id="base_link",
                           translation=Vector3(x=st.x, y=st.y, z=0.0), rotation=_quat(st.yaw)),
            FrameTransform(timestamp=_ts(now), parent_frame_id="base_link", child_frame_id="laser",
                           translation=Vector3(x=m.x, y=m.y, z=m.z), rotation=_quat(m.yaw)),
        ]), log_time=now)
        self.counts["state"] += 1
        self.ch_cars.log(SceneUpdate(entities=[self._box("ego", st.x, st.y, st.yaw, self.car_params.length,
                                                         self.car_params.width, (0.2, 0.5, 0.9, 0.8), now)]),
                         log_time=now)

    def _box(self, ident: str, x: float, y: float, yaw: float, length: float, width: float, rgba, now: int):
        from foxglove.messages import Color, CubePrimitive, Duration, Pose, SceneEntity, Vector3

        return SceneEntity(timestamp=_ts(now), frame_id="odom", id=ident, lifetime=Duration(sec=1, nsec=0),
                           cubes=[CubePrimitive(pose=Pose(position=Vector3(x=x, y=y, z=0.1), orientation=_quat(yaw)),
                                                size=Vector3(x=length, y=width, z=0.2),
                                                color=Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3]))])

    def _on_obstacles(self, obs: ObstacleStates) -> None:
        from foxglove.messages import SceneUpdate

        now = time.time_ns()
        ents = [self._box(f"obstacle-{o.id}", o.x, o.y, o.yaw, o.length, o.width, (0.9, 0.3, 0.2, 0.8), now)
                for o in obs.obstacles]
        self.ch_cars.log(SceneUpdate(entities=ents), log_time=now)
        self.counts["obstacles"] += 1

    def _log_walls(self, now: int) -> None:
        from foxglove.messages import (Color, LinePrimitive, LinePrimitiveLineType, Point3, Pose, SceneEntity,
                                       SceneUpdate, Vector3)

        pts = []
        for x0, y0, x1, y1 in self._walls:
            pts += [Point3(x=float(x0), y=float(y0), z=0.0), Point3(x=float(x1), y=float(y1), z=0.0)]
        ent = SceneEntity(timestamp=_ts(now), frame_id="odom", id="walls", lines=[LinePrimitive(
            type=LinePrimitiveLineType.LineList,
            pose=Pose(position=Vector3(x=0.0, y=0.0, z=0.0), orientation=_quat(0.0)),
            thickness=0.05, scale_invariant=False, points=pts, color=Color(r=0.8, g=0.8, b=0.8, a=1.0))])
        self.ch_walls.log(SceneUpdate(entities=[ent]), log_time=now)

    def _on_cmd(self, cmd: DriveCommand) -> None:
        now = time.time_ns()
        self.ch_cmd.log({"a_throttle": cmd.a_throttle, "a_steer": cmd.a_steer, "throttle": cmd.throttle,
                         "steering_angle": cmd.steering_angle, "source": cmd.source, "scan_seq": cmd.scan_seq},
                        log_time=now)
        with self._lock:
            t_scan = self._scan_arrival.pop((cmd.scan_seq, cmd.scan_stamp_ns), None)
        if t_scan is not None:
            self.ch_latency.log({"scan_to_cmd_ms": (time.monotonic_ns() - t_scan) / 1e6,
                                 "compute_ms": cmd.compute_ns / 1e6}, log_time=now)
        self.counts["cmd"] += 1

    # ------------------------------------------------------------------ life cycle
    def step(self) -> None:
        # the walls do not change: re-sent every 2 s for viewers that connect later
        if self._walls is not None and time.monotonic() - self._last_walls > 2.0:
            self._last_walls = time.monotonic()
            self._log_walls(time.time_ns())
        self.stop_event.wait(0.2)

    def info(self) -> dict[str, Any]:
        return {"url": f"ws://{self.host}:{self.server.port}" if self.server else "", "world": self.world_name,
                "mcap": self.mcap_path or "", "messages": dict(self.counts)}

    def close(self) -> None:
        try:
            super().close()
        finally:
            if self.server is not None:
                self.server.stop()
            if self._mcap is not None:
                self._mcap.close()


OPTIONS = {"host": "host", "port": "port", "world": "world"}
"""Typed options -> viz.<field> (validated as the config is: a bad one exits 2 naming both)."""
SECTION = "viz"


def run(args: argparse.Namespace, cfg: Config) -> int:
    v = apply_options(cfg, SECTION, args, OPTIONS).viz
    try:
        viz = Viz(cfg, v.host, v.port, args.mcap, v.world)
    except (ImportError, ValueError, FileNotFoundError) as e:
        print(f"racecav viz: {e}")
        return 2
    return viz.run()
