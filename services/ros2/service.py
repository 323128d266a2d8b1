"""``racecav ros2``: the car's bus as ROS 2 topics (rmw_zenoh or zenoh-bridge-ros2dds), and ROS
``/drive`` as a command input.

Out (racecav key -> ROS 2 topic, CDR):
  racecav/<car>/scan  -> /scan       sensor_msgs/msg/LaserScan
  racecav/<car>/state -> /odom       nav_msgs/msg/Odometry
  racecav/<car>/cmd   -> /drive_out  ackermann_msgs/msg/AckermannDriveStamped
In (ROS 2 -> racecav):
  /drive (AckermannDriveStamped) -> racecav/<car>/drive_ros (DriveCommand, source "ros"), which
  the actuator's mux ranks below teleop and above the controller (F1TENTH's ackermann_mux order).

In rmw_zenoh mode the node ``/racecav`` and its publishers and subscription hold the liveliness
tokens ROS 2's graph is made of, so ``ros2 node list`` / ``ros2 topic list`` / ``ros2 topic echo
/scan`` work against the same Zenoh network; keys, attachment and tokens are described in
:mod:`racecav.services.ros2.rmw`. Outgoing messages are converted (6-10 us each,
``racecav bench record``) and sent in 10 ms batches by the service loop, at niceness +10
(``ros2.batch_s``, ``ros2.nice``): the mirror stays off the scan -> command burst. Invalid input
on either side is counted and dropped.
"""

from __future__ import annotations

import argparse
import queue
import time
from typing import Any, Callable

from racecav.common import keys
from racecav.common.bus import Service, zenoh_config
from racecav.common.config import Config, apply_options
from racecav.common.messages import DriveCommand, Message, Scan, VehicleState


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mode", choices=["rmw_zenoh", "humble", "bridge"],
                   help="ROS 2 flavour (default: ros2.mode = rmw_zenoh, i.e. Jazzy or later)")
    p.add_argument("--ros-connect", action="append", metavar="ENDPOINT",
                   help="Zenoh endpoint of the ROS side, e.g. tcp/127.0.0.1:7448 (repeatable; "
                        "default: ros2.connect, empty = the car's own router)")
    p.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID (default: ros2.domain_id)")
    p.epilog = ("examples:\n"
                "  racecav ros2                                  # mirror onto the car's router\n"
                "  racecav ros2 --ros-connect tcp/127.0.0.1:7448 # rmw_zenohd on its own port\n"
                "  racecav ros2 --mode humble                    # ROS 2 Humble with rmw_zenoh\n"
                "  racecav ros2 --mode bridge                    # zenoh-bridge-ros2dds keys")
    p.formatter_class = argparse.RawDescriptionHelpFormatter


class RosTopicOut:
    """One ROS-side publisher: key, liveliness token, attachment sequence."""

    def __init__(self, svc: "Ros2Service", topic: str, type_name: str):
        self.topic, self.type_name = topic, type_name
        g = svc.graph
        self.key = g.data_key(topic, type_name)
        self.token, self.gid = g.entity_token("MP", topic, type_name)
        self._attach = g.mode != "bridge"
        self._pub = svc.ros.declare_publisher(self.key)
        svc._ros_declared.append(self._pub)
        if self.token is not None:
            svc._ros_declared.append(svc.ros.liveliness().declare_token(self.token))
        self.seq = 0

    def put(self, cdr: bytes) -> None:
        from racecav.services.ros2.rmw import attachment

        self.seq += 1
        if self._attach:
            self._pub.put(cdr, attachment=attachment(self.seq, time.time_ns(), self.gid))
        else:
            self._pub.put(cdr)


class Ros2Service(Service):
    """The mirror. :param cfg: whole configuration (section ``ros2``)."""

    def __init__(self, cfg: Config):
        super().__init__(cfg, "ros2")
        from racecav.common.vehicle import load_car
        from racecav.services.ros2.msgs import Converter

        self.rcfg = cfg.ros2
        if self.rcfg.drive_in_topic and self.rcfg.drive_in_topic == self.rcfg.drive_out_topic:
            raise ValueError("ros2.drive_out_topic: must differ from drive_in_topic (the mirror "
                             "would feed its own commands back)")
        self.conv = Converter(load_car(self.rcfg.car), self.rcfg.base_frame)
        self.counts: dict[str, int] = {}
        self._ros_declared: list[Any] = []
        self._own_ros_session = False
        self.ros = None
        self.graph = None
        self.drive_in_key = ""
        self.outs: dict[str, RosTopicOut] = {}
        self._q: queue.SimpleQueue = queue.SimpleQueue()

    def _stamp(self, msg: Message, arrival_ns: int) -> int:
        return arrival_ns if self.rcfg.stamps == "wall" else msg.stamp_ns

    def setup(self) -> None:
        import os

        import zenoh

        from racecav.services.ros2 import msgs
        from racecav.services.ros2.rmw import Graph

        r = self.rcfg
        if r.nice:
            os.nice(r.nice)  # below the controllers: the mirror is not on the control path
        if r.connect:  # a separate Zenoh network (an rmw_zenohd router): its own session
            bus = self.cfg.bus.model_copy(update={"connect": list(r.connect), "mode": "client",
                                                  "user": None, "password": None})
            self.ros = zenoh.open(zenoh_config(bus))
            self._own_ros_session = True
        else:
            self.ros = self.session
        self.graph = Graph(r.mode, r.domain_id, str(self.ros.info.zid()), r.node, r.namespace,
                           r.bridge_prefix)
        node_token = self.graph.node_token()
        if node_token is not None:
            self._ros_declared.append(self.ros.liveliness().declare_token(node_token))

        routes: list[tuple[str, str, str, type[Message], Callable[[Any, int], bytes]]] = [
            (r.scan_topic, msgs.LASER_SCAN, keys.SCAN, Scan, self.conv.scan),
            (r.odom_topic, msgs.ODOMETRY, keys.STATE, VehicleState, self.conv.odometry),
            (r.drive_out_topic, msgs.ACKERMANN_STAMPED, keys.CMD, DriveCommand, self.conv.drive),
        ]
        for topic, type_name, leaf, cls, convert in routes:
            if topic:
                out = RosTopicOut(self, topic, type_name)
                self.outs[topic] = out
                self.counts[topic] = 0
                self.subscribe(self.topic(leaf), cls, self._mirror(out, convert))

        if r.drive_in_topic:
            self.drive_pub = self.publisher(self.topic(keys.DRIVE_ROS), command=True)
            self.drive_in_key = self.graph.data_key(r.drive_in_topic, msgs.ACKERMANN_STAMPED)
            token, _gid = self.graph.entity_token("MS", r.drive_in_topic, msgs.ACKERMANN_STAMPED)
            self.counts[r.drive_in_topic] = 0
            self._ros_declared.append(self.ros.declare_subscriber(self.drive_in_key, self._on_drive))
            if token is not None:
                self._ros_declared.append(self.ros.liveliness().declare_token(token))

    def _mirror(self, out: RosTopicOut, convert) -> Callable[[Message], None]:
        def on_msg(msg: Message) -> None:
            if self.rcfg.batch_s > 0:  # converted and sent by the loop, after the control path's burst
                self._q.put((out, convert, msg, time.time_ns()))
            else:
                self._send(out, convert, msg, time.time_ns())

        return on_msg

    def _send(self, out: RosTopicOut, convert, msg: Message, arrival_ns: int) -> None:
        try:
            out.put(convert(msg, self._stamp(msg, arrival_ns)))
        except Exception as e:  # a conversion bug must not kill the thread
            self.invalid += 1
            self._record_error(f"mirror {out.topic}: {type(e).__name__}: {e}")
            return
        self.counts[out.topic] += 1
        self.published += 1

    def step(self) -> None:
        self.stop_event.wait(self.rcfg.batch_s if self.rcfg.batch_s > 0 else 0.2)
        while True:
            try:
                self._send(*self._q.get_nowait())
            except queue.Empty:
                return

    def _on_drive(self, sample) -> None:
        self.received += 1
        topic = self.rcfg.drive_in_topic
        data = sample.payload.to_bytes()
        if len(data) > self.rcfg.max_payload_bytes:  # refused before rosbags parses it
            self.invalid += 1
            self._record_error(f"invalid {topic}: payload of {len(data)} bytes exceeds "
                               f"ros2.max_payload_bytes ({self.rcfg.max_payload_bytes})")
            return
        try:
            cmd = self.conv.command_from_drive(data, self.counts[topic],
                                               getattr(self.cfg.actuator, "ros_source", "ros"))
        except ValueError as e:
            self.invalid += 1
            self._record_error(f"invalid {topic}: {e}")
            return
        self.counts[topic] += 1
        self.drive_pub.put(cmd)

    def info(self) -> dict[str, Any]:
        keys_ = {t: o.key for t, o in self.outs.items()}
        if self.drive_in_key:
            keys_[self.rcfg.drive_in_topic] = self.drive_in_key
        return {"mode": self.rcfg.mode, "domain_id": self.rcfg.domain_id,
                "ros_connect": list(self.rcfg.connect) or "bus", "keys": keys_, "messages": dict(self.counts)}

    def close(self) -> None:
        for obj in reversed(self._ros_declared):
            try:
                obj.undeclare()
            except Exception as e:  # already gone; keep closing the rest
                self.log.debug("undeclare: %s", e)
        self._ros_declared.clear()
        if self._own_ros_session and self.ros is not None:
            self.ros.close()
        self.ros = None
        super().close()


OPTIONS = {"mode": "mode", "ros_connect": "connect", "domain_id": "domain_id"}
"""Typed options -> ros2.<field> (validated as the config is: a bad one exits 2 naming both)."""
SECTION = "ros2"


def run(args: argparse.Namespace, cfg: Config) -> int:
    cfg = apply_options(cfg, SECTION, args, OPTIONS)
    try:
        svc = Ros2Service(cfg)
    except (ImportError, ValueError, FileNotFoundError) as e:
        print(f"racecav ros2: {e}")
        return 2
    return svc.run()
