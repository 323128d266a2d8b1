"""The policy's lidar: 170 rays over the frontal 90 degrees, and the ONE preprocessing contract.

Ray order follows REP-103 / sensor_msgs/LaserScan: counter-clockwise, index 0 is the rightmost
ray at ``angle_min = -pi/4``, index 169 the leftmost at ``+pi/4``; angles are in the laser frame.

Two representations, one conversion each way:
- the Scan message (sim and real alike): metres, float32, no return = ``+inf`` (REP-117), never 0
  or NaN: :func:`scan_ranges` turns raw ray results into it;
- the policy observation: :func:`sanitize` maps a Scan's ranges to finite values in
  ``[range_min, range_max]`` (no return / beyond range -> range_max, closer than range_min ->
  range_min). Every consumer (training env, policy service, baseline) calls it.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator


class LidarSpec(BaseModel):
    """Geometry and range of the (virtual) scan the policy consumes."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    n_rays: int = Field(170, ge=2)
    fov: float = Field(np.pi / 2, gt=0, le=2 * np.pi)
    """Angular span from the first to the last ray (rad)."""
    angle_min: float = -np.pi / 4
    """Angle of ray 0 (rightmost), rad, CCW positive."""
    range_min: float = Field(0.05, ge=0)
    range_max: float = Field(12.0, gt=0)
    scan_rate_hz: float = Field(10.0, gt=0)

    @model_validator(mode="after")
    def _check(self) -> "LidarSpec":
        if self.range_max <= self.range_min:
            raise ValueError("range_max: must exceed range_min")
        return self

    @property
    def angle_max(self) -> float:
        return self.angle_min + self.fov

    @property
    def angle_increment(self) -> float:
        return self.fov / (self.n_rays - 1)


PAPER_INCREMENT = (np.pi / 2) / 169
"""The paper's ray spacing: 170 rays over 90 degrees."""
VIEWS: dict[str, LidarSpec] = {
    # the paper's view: 170 rays over the frontal 90 degrees (the car's scan on the bus)
    "paper": LidarSpec(),
    # every second ray of the paper's grid extended to +-89.7 deg (169 rays, 1.07 deg apart): a car
    # crossing at a shallow angle stays at a constant bearing of about 50 deg on a collision
    # course, outside the paper's +-45 deg (docs/training.md). The RPLIDAR S2 sees 360 deg.
    "wide": LidarSpec(n_rays=169, fov=336 * PAPER_INCREMENT, angle_min=-168.5 * PAPER_INCREMENT),
}
"""Named views a policy can be trained on (EnvConfig.lidar, the policy's metadata "lidar")."""
WIDE_SCAN = LidarSpec(n_rays=338, fov=337 * PAPER_INCREMENT, angle_min=-168.5 * PAPER_INCREMENT)
"""The scan that holds every view: the paper's grid over +-89.7 deg (what the sim and the sensor
publish when a consumer needs the wide view; each consumer takes its own with view_index)."""


def published_scan(car_lidar: LidarSpec, kind: str) -> LidarSpec:
    """The scan the sim or the sensor publishes: "paper" = the car's lidar, "wide" = WIDE_SCAN's
    rays with the car's ranges and rate (SimConfig.scan, SensorConfig.scan)."""
    if kind == "paper":
        return car_lidar
    if kind != "wide":
        raise ValueError(f"scan: expected 'paper' or 'wide', got {kind!r}")
    return with_rays(car_lidar, WIDE_SCAN)


def with_rays(base: LidarSpec, rays: LidarSpec) -> LidarSpec:
    """``base`` (a car's lidar: range limits, rate) with the rays of ``rays`` (count, span, start)."""
    return base.model_copy(update={k: getattr(rays, k) for k in ("n_rays", "fov", "angle_min")})


def view_index(scan: LidarSpec, view: LidarSpec, tol: float = 1e-4) -> np.ndarray:
    """Indices of ``view``'s rays within ``scan``'s: ``ranges[view_index(...)]`` is the view.

    :raises ValueError: when a ray of the view is not a ray of the scan (within ``tol`` rad).
    """
    a_scan, a_view = ray_angles(scan).astype(np.float64), ray_angles(view).astype(np.float64)
    idx = np.rint((a_view - scan.angle_min) / scan.angle_increment).astype(np.int64)
    ok = (idx >= 0) & (idx < scan.n_rays)
    if not ok.all() or np.abs(a_scan[np.clip(idx, 0, scan.n_rays - 1)] - a_view).max() > tol:
        raise ValueError(f"lidar: a scan of {scan.n_rays} rays from {np.degrees(scan.angle_min):.2f} deg "
                         f"every {np.degrees(scan.angle_increment):.3f} deg does not hold the view of "
                         f"{view.n_rays} rays from {np.degrees(view.angle_min):.2f} deg every "
                         f"{np.degrees(view.angle_increment):.3f} deg")
    return idx


def ray_angles(spec: LidarSpec | None = None) -> np.ndarray:
    """Ray angles in the laser frame, float32[n_rays], CCW, index 0 = rightmost."""
    spec = spec or LidarSpec()
    return (spec.angle_min + spec.angle_increment * np.arange(spec.n_rays)).astype(np.float32)


def scan_ranges(distances, hit, spec: LidarSpec | None = None) -> np.ndarray:
    """Raw ray results -> Scan ranges: float32, metres, +inf where nothing was hit in range.

    :param distances: distance from the sensor to the hit (m), any value where ``hit`` is False.
    :param hit: bool array, True where the ray hit something within range_max.
    """
    spec = spec or LidarSpec()
    d = np.asarray(distances, dtype=np.float32)
    ok = np.asarray(hit, dtype=bool) & np.isfinite(d) & (d <= spec.range_max)
    return np.where(ok, d, np.float32(np.inf)).astype(np.float32)


def sanitize(ranges, spec: LidarSpec | None = None) -> np.ndarray:
    """Scan ranges -> policy observation (float32, same shape, also batched (..., n_rays)).

    NaN, +inf and anything beyond range_max become range_max (nothing seen); finite values
    below range_min become range_min (something touching the sensor is as close as it gets).
    """
    spec = spec or LidarSpec()
    r = np.asarray(ranges, dtype=np.float32)
    rmax = np.float32(spec.range_max)
    # Two ufuncs instead of isfinite/where/clip/astype: this runs on every control step.
    # NaN and +inf compare False -> range_max; -inf is excluded explicitly (non-finite).
    out = np.where((r < rmax) & (r > -np.inf), r, rmax)
    return np.maximum(out, np.float32(spec.range_min), out=out)


def make_scan(ranges, stamp_ns: int, seq: int, source: str, spec: LidarSpec | None = None,
              frame_id: str = "laser"):
    """Build the Scan message (the same for sim and real; only ``source`` differs).

    :param ranges: float32[n_rays] in Scan form (+inf = no return), see :func:`scan_ranges`.
    :param source: "sim" or "real".
    """
    from racecav.common.messages import Scan

    spec = spec or LidarSpec()
    return Scan(stamp_ns=stamp_ns, seq=seq, source=source, frame_id=frame_id,
                angle_min=spec.angle_min, angle_max=spec.angle_max,
                angle_increment=spec.angle_increment, scan_time=1.0 / spec.scan_rate_hz,
                range_min=spec.range_min, range_max=spec.range_max,
                ranges=np.asarray(ranges, dtype=np.float32))


def fill_holes(th: np.ndarray, r: np.ndarray, ok: np.ndarray, max_gap_deg: float) -> np.ndarray:
    """Samples not ``ok`` replaced by linear interpolation in angle between the nearest good
    samples when those are at most ``max_gap_deg`` apart; +inf where the hole is wider. The one
    hole filling of the project: the sensor service's (services/sensor/preprocess.py) and the
    sim's for perturbed scans (common/perturb.py).

    :param th: sorted angles (rad). :param r: ranges (m). :param ok: the trustworthy samples.
    """
    rr = np.asarray(r, dtype=np.float64)
    out = np.where(ok, rr, np.inf)
    bad = np.flatnonzero(~ok)
    good = np.flatnonzero(ok)
    if bad.size and good.size >= 2:
        # Nearest good sample on each side of every bad one.
        right = np.searchsorted(good, bad)
        has = (right > 0) & (right < good.size)
        lo = good[np.clip(right - 1, 0, good.size - 1)]
        hi = good[np.clip(right, 0, good.size - 1)]
        gap = th[hi] - th[lo]
        fill = has & (gap <= math.radians(max_gap_deg)) & (gap > 0)
        w = np.where(fill, (th[bad] - th[lo]) / np.where(gap > 0, gap, 1.0), 0.0)
        out[bad[fill]] = (rr[lo] + w * (rr[hi] - rr[lo]))[fill]
    return out
