"""`racecav sensor`: the real lidar as a service. Publishes a Scan (source "real") per revolution.

The driver thread reads the serial port and hands over whole revolutions (newest only: a stale
revolution is worthless); the service loop preprocesses the newest one into the policy's 170
rays and publishes it on racecav/<car>/scan, the same key and message the simulator uses.
"""

from __future__ import annotations

import argparse
import threading
import time

from racecav.common.bus import Service
from racecav.common.config import Config
from racecav.common.keys import SCAN


class SensorService(Service):
    """:param port: overrides cfg.sensor.port."""

    def __init__(self, cfg: Config, port: str | None = None, name: str = "sensor"):
        super().__init__(cfg, name)
        self.scfg = cfg.sensor
        self.port = port or self.scfg.port
        self._cond = threading.Condition()
        self._rev = None
        self._driver = None
        self._thread: threading.Thread | None = None
        self._seq = 0
        self.preprocess_us = 0.0

    def setup(self) -> None:
        from racecav.common.lidar import published_scan
        from racecav.common.vehicle import load_car
        from racecav.services.sensor.preprocess import PreprocessParams, cut_angle_deg
        from racecav.services.sensor.rplidar_driver import RplidarDriver

        car = load_car(self.scfg.car)
        self.spec = published_scan(car.lidar, self.scfg.scan)
        self.mount_yaw = car.lidar_mount.yaw if self.scfg.mount_yaw_rad is None else self.scfg.mount_yaw_rad
        self.params = PreprocessParams(max_gap_deg=self.scfg.max_gap_deg, spike_abs_m=self.scfg.spike_abs_m,
                                       spike_rel=self.scfg.spike_rel, downsample=self.scfg.downsample)
        self.pub = self.publisher(self.topic(SCAN))
        self._driver = RplidarDriver(
            self.port, self._on_revolution, baudrate=self.scfg.baudrate, scan_mode=self.scfg.scan_mode,
            motor_rpm=self.scfg.motor_rpm, cut_deg=cut_angle_deg(self.spec, self.mount_yaw),
            **self.scfg.driver_timings())
        self._thread = self._driver.start_thread()

    def _on_revolution(self, rev) -> None:
        # Driver thread: hand over and return at once (the port must keep being read).
        with self._cond:
            if self._rev is not None:
                self.dropped += 1
            self._rev = (rev, int(rev.t_end * 1e9))  # when its last bytes were read (monotonic)
            self._cond.notify()

    def step(self) -> None:
        from racecav.services.sensor.preprocess import revolution_to_scan

        with self._cond:
            if self._rev is None and not self._cond.wait(0.2):
                return
            item, self._rev = self._rev, None
        if item is None:
            return
        rev, t_ns = item
        self.received += 1
        t0 = time.perf_counter()
        try:
            scan = revolution_to_scan(rev.angle_deg, rev.dist_mm, t_ns, self._driver.us_per_sample, self._seq,
                                      self.spec, self.mount_yaw, self.params)
        except Exception as e:  # a bad revolution is counted, never fatal
            self.invalid += 1
            self._record_error(f"preprocess: {e}")
            return
        self.preprocess_us = (time.perf_counter() - t0) * 1e6
        self.pub.put(scan)
        self._seq += 1

    def info(self) -> dict:
        d = self._driver.status() if self._driver else {}
        d["preprocess_us"] = round(self.preprocess_us, 1)
        d["mount_yaw"] = getattr(self, "mount_yaw", None)
        return d

    def teardown(self) -> None:
        if self._driver is not None:
            self._driver.stop_event.set()
        if self._thread is not None:
            self._thread.join(3.0)  # the driver stops the scan and the motor on its way out


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--port", help="serial device (default: sensor.port, /dev/rplidar)")
    p.add_argument("--name", default="sensor", help="service name (keys racecav/<car>/<name>/...)")


def run(args: argparse.Namespace, cfg: Config) -> int:
    return SensorService(cfg, port=args.port, name=args.name).run()
