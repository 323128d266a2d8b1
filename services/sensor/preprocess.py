"""Real-scan preprocessing, as the paper did on hardware, into the Scan the simulator publishes.

One revolution of the RPLIDAR (device angles: clockwise degrees) becomes the policy's 170 rays
over the frontal 90 degrees (:mod:`racecav.common.lidar`: REP-103, counter-clockwise, index 0 =
rightmost, no return = +inf):

1. angles to the laser frame: ``theta = -radians(a) + mount_yaw`` (the device turns clockwise;
   ``mount_yaw`` is where the device's 0 deg mark points, from the car file's lidar_mount.yaw);
2. outliers marked: zero (the device's "no return"), NaN, outside [range_min, range_max], and
   isolated spikes (one sample far from both neighbours while the neighbours agree);
3. outliers replaced by linear interpolation in angle between the nearest good samples, when
   those are at most ``max_gap_deg`` apart (a lost capsule is 4.5 deg at 10 Hz). Wider holes
   stay "no return" (+inf): interpolating across a long run of zeros would invent a wall;
4. the frontal +-45 deg selected by angle and downsampled to the rays' angles ("interp": linear
   between the two bracketing samples, like the simulator's single ray per angle; "nearest"; or
   "min": the nearest return within each ray's angular bin, the conservative choice).

The sweep is clockwise, so ranges[0] (rightmost) is measured last: ``stamp_ns`` is the time of
ranges[0] as the conventions ask and ``time_increment`` is negative.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from racecav.common.lidar import LidarSpec, fill_holes, make_scan, ray_angles, scan_ranges


@dataclass(frozen=True)
class PreprocessParams:
    """:param max_gap_deg: widest hole (between good samples) filled by interpolation.
    :param spike_abs_m: a spike differs from both neighbours by more than this ...
    :param spike_rel: ... and by more than this fraction of the neighbours' range.
    :param downsample: "interp", "nearest" or "min" (see module doc).
    """

    max_gap_deg: float = 6.0
    spike_abs_m: float = 0.3
    spike_rel: float = 0.15
    downsample: Literal["interp", "nearest", "min"] = "interp"


def device_to_laser(angle_deg: np.ndarray, mount_yaw: float = 0.0) -> np.ndarray:
    """Device angles (clockwise degrees) to laser-frame angles (CCW rad, in [-pi, pi))."""
    th = -np.radians(np.asarray(angle_deg, dtype=np.float64)) + mount_yaw
    return np.mod(th + math.pi, 2 * math.pi) - math.pi


def cut_angle_deg(spec: LidarSpec, mount_yaw: float = 0.0, margin_deg: float = 3.0) -> float:
    """Device angle at which to cut revolutions so the frontal sector is contiguous and ends it.

    The device sweeps clockwise: left edge first, right edge (angle_min) last. Cutting
    ``margin_deg`` past the right edge publishes the frontal rays as soon as they are all
    measured, with enough neighbours for interpolation at the edge.
    """
    edge = spec.angle_min - math.radians(margin_deg)  # laser frame, just right of the sector
    return math.degrees(mount_yaw - edge) % 360.0


def _spikes(r: np.ndarray, ok: np.ndarray, p: PreprocessParams) -> np.ndarray:
    """Isolated spikes among consecutive good samples (sorted by angle)."""
    out = np.zeros_like(ok)
    if r.shape[0] < 3:
        return out
    a, b, c = r[:-2], r[1:-1], r[2:]
    good3 = ok[:-2] & ok[1:-1] & ok[2:]
    thr = np.maximum(p.spike_abs_m, p.spike_rel * np.minimum(a, c))
    spike = good3 & (np.abs(b - a) > thr) & (np.abs(b - c) > thr) & (np.abs(a - c) <= thr) \
        & (np.sign(b - a) == np.sign(b - c))
    out[1:-1] = spike
    return out


def clean(theta: np.ndarray, r: np.ndarray, spec: LidarSpec, p: PreprocessParams) -> tuple[np.ndarray, np.ndarray]:
    """Sort by angle, mark outliers, fill short holes by interpolation.

    :param theta: laser-frame angles (rad).
    :param r: ranges (m); 0 or NaN = no return.
    :returns: sorted angles and ranges, +inf where nothing trustworthy is left.
    """
    order = np.argsort(theta, kind="stable")
    th = theta[order]
    rr = np.asarray(r, dtype=np.float64)[order]
    ok = np.isfinite(rr) & (rr >= spec.range_min) & (rr <= spec.range_max)
    ok &= ~_spikes(rr, ok, p)
    return th, fill_holes(th, rr, ok, p.max_gap_deg)


def downsample(th: np.ndarray, r: np.ndarray, spec: LidarSpec, p: PreprocessParams) -> np.ndarray:
    """Cleaned samples (sorted angles) -> ranges at the spec's ray angles (+inf = no return)."""
    rays = ray_angles(spec).astype(np.float64)
    n = rays.shape[0]
    if th.size < 2:
        return np.full(n, np.inf, np.float32)
    max_gap = math.radians(p.max_gap_deg)
    j = np.clip(np.searchsorted(th, rays), 1, th.size - 1)
    lo, hi = j - 1, j
    gap = th[hi] - th[lo]
    covered = (gap <= max_gap) & (th[lo] <= rays) & (rays <= th[hi])
    near = np.where(rays - th[lo] <= th[hi] - rays, lo, hi)
    if p.downsample == "nearest":
        out = r[near]
    else:
        w = np.where(gap > 0, (rays - th[lo]) / np.where(gap > 0, gap, 1.0), 0.0)
        both = np.isfinite(r[lo]) & np.isfinite(r[hi])
        with np.errstate(invalid="ignore"):  # inf - inf where a neighbour is a hole: not used
            out = np.where(both, r[lo] + w * (r[hi] - r[lo]), r[near])
        if p.downsample == "min":
            half = spec.angle_increment / 2
            a = np.searchsorted(th, rays - half, side="left")
            b = np.searchsorted(th, rays + half, side="right")
            for k in np.flatnonzero(b > a):  # 170 small slices: cheap
                out[k] = min(out[k], float(np.min(r[a[k]:b[k]])))
    out = np.where(covered, out, np.inf)
    return scan_ranges(out, np.isfinite(out), spec)


def preprocess(angle_deg: np.ndarray, dist_mm: np.ndarray, spec: LidarSpec, mount_yaw: float = 0.0,
               params: PreprocessParams = PreprocessParams()) -> np.ndarray:
    """One revolution (device angles, mm) -> float32[n_rays] Scan ranges (+inf = no return)."""
    theta = device_to_laser(angle_deg, mount_yaw)
    lo = spec.angle_min - math.radians(p_margin(params))
    hi = spec.angle_max + math.radians(p_margin(params))
    sel = (theta >= lo) & (theta <= hi)
    r = np.asarray(dist_mm, dtype=np.float64)[sel] / 1000.0
    th, rr = clean(theta[sel], r, spec, params)
    return downsample(th, rr, spec, params)


def p_margin(p: PreprocessParams) -> float:
    """Degrees kept outside the sector so edge rays have neighbours to interpolate from."""
    return p.max_gap_deg


def revolution_to_scan(angle_deg: np.ndarray, dist_mm: np.ndarray, t_end_ns: int, us_per_sample: float,
                       seq: int, spec: LidarSpec, mount_yaw: float = 0.0,
                       params: PreprocessParams = PreprocessParams()):
    """A revolution -> the Scan message (source "real"), stamped at the time of ranges[0].

    Sample times are reconstructed from the time the revolution's last bytes were read and the
    mode's sample period (the device sends each capsule right after measuring it).

    :param t_end_ns: monotonic time (ns) at which the revolution's last sample was read.
    :param us_per_sample: the scan mode's sample period (GET_LIDAR_CONF 71); 0 = unknown.
    """
    ranges = preprocess(angle_deg, dist_mm, spec, mount_yaw, params)
    n = len(angle_deg)
    dt_ns = us_per_sample * 1e3
    theta = device_to_laser(angle_deg, mount_yaw)
    # Index (in arrival order) of the samples closest to the first and last rays.
    i0 = int(np.argmin(np.abs(theta - spec.angle_min)))
    i1 = int(np.argmin(np.abs(theta - spec.angle_max)))
    stamp = int(t_end_ns - (n - 1 - i0) * dt_ns)
    scan = make_scan(ranges, stamp_ns=max(stamp, 0), seq=seq, source="real", spec=spec)
    if dt_ns > 0:
        scan.time_increment = float((i1 - i0) * dt_ns * 1e-9 / (spec.n_rays - 1))
        scan.scan_time = float(n * dt_ns * 1e-9)
    return scan
