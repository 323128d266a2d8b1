"""What every controller service shares: newest scan in, one DriveCommand per usable scan out.

The DRL policy (``racecav policy``) and the MPC-APF baseline (``racecav baseline``) both subclass
:class:`ControllerService`, so they listen and answer on the same keys with the same message and
the same rules; the simulator or the car cannot tell which one runs (only ``source`` differs).

Rules for a scan (counted in the status ``info``, never a command):
- malformed: the scan does not hold the controller's view (ray count, angle_min, angle_increment
  of its LidarSpec: the car's, or the policy's metadata "lidar"; a wider scan holding those rays
  is fine, the view is taken from it) -> ``malformed``; undecodable payloads are the bus's
  ``invalid``;
- stale: it arrived more than ``max_scan_age_s`` ago (wall clock) by the time it is answered,
  or, for a ``source = "real"`` scan (stamped with this host's monotonic clock), its stamp is
  older than that -> ``stale``;
- no scan: no command (the car's watchdog brakes).

Where the answer is computed: a controller that answers in microseconds (the policy) answers in
Zenoh's callback thread as the scan arrives (``answer_in_callback``), which saves the wake-up of
the service loop; a slow one (the MPC, milliseconds) must not hold the callback thread, so it
takes the newest scan from the loop and scans arriving meanwhile are dropped (counted).
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np

from racecav.common import keys
from racecav.common.bus import Service
from racecav.common.config import Config
from racecav.common.lidar import LidarSpec, view_index
from racecav.common.messages import INT64_MAX, DriveCommand, Scan
from racecav.common.vehicle import CarParams, brake_from_action, steer_from_action, throttle_from_action

GEOMETRY_TOL = 1e-4
"""rad: tolerance on angle_min / angle_increment when checking a scan's geometry."""


def scan_problem(scan: Scan, spec: LidarSpec) -> str | None:
    """Why ``scan`` is not the observation geometry ``spec`` describes, or None if it is."""
    n = scan.ranges.shape[0]
    if n != spec.n_rays:
        return f"ranges: {n} rays, the policy's lidar has {spec.n_rays}"
    if abs(scan.angle_min - spec.angle_min) > GEOMETRY_TOL:
        return f"angle_min: {scan.angle_min:.5f} rad, expected {spec.angle_min:.5f}"
    if abs(scan.angle_increment - spec.angle_increment) > GEOMETRY_TOL:
        return f"angle_increment: {scan.angle_increment:.6f} rad, expected {spec.angle_increment:.6f}"
    return None


def scan_view(scan: Scan, spec: LidarSpec) -> np.ndarray | None:
    """Indices of the view ``spec`` within ``scan``'s rays; None when the scan is exactly that
    view (the usual case: no copy). A wider scan (common/lidar.WIDE_SCAN) holds every named view.

    :raises ValueError: why the scan does not hold the view.
    """
    if scan_problem(scan, spec) is None:
        return None
    n = scan.ranges.shape[0]
    if n < 2:
        raise ValueError(f"ranges: {n} rays, the policy's lidar has {spec.n_rays}")
    geom = LidarSpec(n_rays=n, fov=scan.angle_increment * (n - 1), angle_min=scan.angle_min,
                     range_min=spec.range_min, range_max=spec.range_max)
    try:
        return view_index(geom, spec, tol=GEOMETRY_TOL)
    except ValueError as e:  # the usual cause: a wide-view policy fed the paper's scan
        raise ValueError(f"{e} (the publisher's scan = \"wide\" holds every view)") from None


def make_command(source: str, a_throttle: float, a_steer: float, car: CarParams, scan: Scan,
                 seq: int, compute_ns: int, brake_below: float | None = None) -> DriveCommand:
    """The DriveCommand answering ``scan`` with the normalised action (a_T, a_delta).

    ``brake_below``: the controller's brake action (policy metadata; None: the paper's action).

    Physical values use the shared mapping of :mod:`racecav.common.vehicle`. The stamp stays in
    the scan's clock domain: this host's monotonic clock for real scans, the scan stamp plus the
    compute time for sim scans (sim time; the two clocks are never mixed).
    """
    a_t = float(np.clip(a_throttle, -1.0, 1.0))
    a_s = float(np.clip(a_steer, -1.0, 1.0))
    stamp = time.monotonic_ns() if scan.source == "real" else scan.stamp_ns + compute_ns
    stamp = min(stamp, INT64_MAX)  # a scan stamped at the very end of int64 must not overflow ours
    return DriveCommand(stamp_ns=stamp, seq=seq, source=source, a_throttle=a_t, a_steer=a_s,
                        throttle=float(throttle_from_action(a_t)),
                        steering_angle=float(steer_from_action(a_s, car)),
                        scan_seq=scan.seq, scan_stamp_ns=scan.stamp_ns, compute_ns=int(compute_ns),
                        scan_source=scan.source, brake=bool(brake_from_action(a_t, brake_below)))


class ControllerService(Service):
    """Base of the controllers: subclasses implement :meth:`act`.

    :param cfg: whole configuration.
    :param name: service name (policy, baseline).
    :param car: car parameters (lidar spec, steering limits).
    :param max_scan_age_s: staleness limit (see the module docstring).
    """

    answer_in_callback = False
    """True: answer each scan in the subscriber callback (only for answers of a few us)."""
    brake_below: float | None = None
    """The controller's brake action: a_T below it brakes (a policy's metadata); None: never."""

    def __init__(self, cfg: Config, name: str, car: CarParams, max_scan_age_s: float,
                 view: LidarSpec | None = None):
        super().__init__(cfg, name)
        self.car_params = car
        self.spec = view or car.lidar
        """The rays the controller sees (its view); a scan may hold more (:func:`scan_view`)."""
        self._views: dict[tuple, np.ndarray | None] = {}  # scan geometry -> view indices
        self._idx: np.ndarray | None = None  # of the scan being answered
        self.max_age_ns = int(max_scan_age_s * 1e9)
        self.counts = {"answered": 0, "stale": 0, "malformed": 0, "no_action": 0}
        self.last_compute_ns = 0
        self.scan_source = ""
        """Source of the newest scan taken ("real": the sensor, "sim": the simulator): with the
        sensor and sim units swapped at runtime, ``racecav state`` shows which one feeds us."""

    def setup(self) -> None:
        self.pub = self.publisher(self.topic(keys.CMD), command=True)
        if self.answer_in_callback:
            self._answer_lock = threading.Lock()  # zenoh may call back from several threads
            self.subscribe(self.topic(keys.SCAN), Scan, self._on_scan)
        else:
            self.scans = self.inbox(self.topic(keys.SCAN), Scan)

    def _on_scan(self, scan: Scan) -> None:
        with self._answer_lock:
            self.answer(scan, time.monotonic_ns())

    def view(self, scan: Scan) -> np.ndarray:
        """The ranges of the controller's view in a scan that passed :meth:`check`."""
        return scan.ranges if self._idx is None else scan.ranges[self._idx]

    def act(self, scan: Scan) -> tuple[float, float] | None:
        """Normalised action (a_T, a_delta) for a valid, fresh scan; None = no command."""
        raise NotImplementedError

    def check(self, scan: Scan, arrival_ns: int) -> bool:
        """True if ``scan`` (arrived at monotonic ``arrival_ns``) may be answered; otherwise
        count why and return False."""
        key = (scan.ranges.shape[0], scan.angle_min, scan.angle_increment)
        if key not in self._views:
            try:
                self._views[key] = scan_view(scan, self.spec)
            except ValueError as e:
                self.counts["malformed"] += 1
                self._record_error(f"malformed scan {scan.seq}: {e}")
                return False
            if len(self._views) > 8:  # garbage geometries must not grow the cache
                self._views = {key: self._views[key]}
        self._idx = self._views[key]
        now = time.monotonic_ns()
        age = now - arrival_ns
        if scan.source == "real":
            age = max(age, now - scan.stamp_ns)
        if age > self.max_age_ns:
            self.counts["stale"] += 1
            self._record_error(f"stale scan {scan.seq}: {age / 1e6:.1f} ms old")
            return False
        return True

    def step(self) -> None:
        if self.answer_in_callback:  # answers happen in the callback; the loop only idles
            self.stop_event.wait(0.2)
            return
        scan = self.scans.take(timeout=0.2)
        if scan is not None:
            self.answer(scan, self.scans.latest()[1])

    def answer(self, scan: Scan, arrival_ns: int) -> None:
        """Check a scan and publish its command (or count why not)."""
        self.scan_source = scan.source
        if not self.check(scan, arrival_ns):
            return
        t0 = time.perf_counter_ns()
        action = self.act(scan)
        compute = time.perf_counter_ns() - t0
        if action is None:
            self.counts["no_action"] += 1
            return
        self.last_compute_ns = compute
        self.pub.put(make_command(self.name, action[0], action[1], self.car_params, scan,
                                  self.counts["answered"], compute, self.brake_below))
        self.counts["answered"] += 1

    def info(self) -> dict[str, Any]:
        return {**self.counts, "last_compute_us": self.last_compute_ns / 1e3, "scan_source": self.scan_source}
