"""Sim-to-real perturbations: one model for both backends and the sim service.

Each perturbation acts where it happens on the car (settings: common/config.PerturbConfig;
presets with their sources: common/data/perturbations.toml, docs/robustness.md):

- the lidar (:func:`perturb_scan`, called by both worlds on the agent's scan): Gaussian range
  noise (absolute and range-proportional, in quadrature), dropped returns (the S2 reports 0; our
  Scan says +inf), then the sensor service's own hole filling (common/lidar.py
  ``fill_holes``, up to SensorConfig.max_gap_deg): the controller sees what the car's would;
- the mount yaw, mass, friction and motor gain (:func:`perturbed_car`: the car the world
  builds; the friction is the floor's, see the worlds), the steering offset (the worlds add it
  to the agent's commanded wheel angle before the servo's limits);
- timing (:func:`command_delay`): latency scan -> command, actuator delay and scan jitter, added
  to the time at which a command takes effect, in sim time (the lockstep sim service; the fast
  world delays its agents' actions the same way).

Random draws come from :func:`trial_rng` of the episode's seed only, so a perturbed lockstep run
repeats exactly.
"""

from __future__ import annotations

import math

import numpy as np

from racecav.common.config import PERTURB_PRESETS_FILE as PRESETS_FILE, PerturbConfig, load_presets, parse_text
from racecav.common.config import perturb_keys as keys
from racecav.common.lidar import LidarSpec, fill_holes, ray_angles, scan_ranges

SALT = 58
"""Mixed into the episode seed: the perturbation's draws never repeat the scenario's."""


def make(text_or_cfg) -> PerturbConfig:
    """A PerturbConfig from its text, a dict or itself (None: the ideal world)."""
    if text_or_cfg is None:
        return PerturbConfig()
    if isinstance(text_or_cfg, PerturbConfig):
        return text_or_cfg
    return PerturbConfig.model_validate(text_or_cfg)


def trial_rng(seed: int, stream: int = 0) -> np.random.Generator:
    """The perturbation's random stream of an episode: a function of its seed only (stream 0:
    the scans; 1: the timing)."""
    return np.random.default_rng([int(seed), SALT, stream])


def perturbed_car(car, p: PerturbConfig):
    """The car as built under ``p``: lidar turned by the mount yaw, mass (and yaw inertia)
    scaled, the agent's wheel speed per throttle times the motor gain."""
    if p.mount_yaw_rad == 0 and p.mass_scale == 1 and p.motor_gain == 1:
        return car
    mount = car.lidar_mount.model_copy(update={"yaw": car.lidar_mount.yaw + p.mount_yaw_rad})
    bicycle = car.bicycle.model_copy(update={"iz": car.bicycle.iz * p.mass_scale})
    return car.model_copy(update={"lidar_mount": mount, "mass": car.mass * p.mass_scale, "bicycle": bicycle,
                                  "agent_speed_scale": car.agent_speed_scale * p.motor_gain})


def lidar_active(p: PerturbConfig) -> bool:
    return bool(p.range_noise_m or p.range_noise_rel or p.dropout)


def perturb_scan(ranges, spec: LidarSpec, p: PerturbConfig, rng: np.random.Generator) -> np.ndarray:
    """Scan ranges (..., n_rays; +inf = no return) as the car's sensor service would publish them
    under ``p``: noise on the returns, dropped returns, then its hole filling. Unchanged (the same
    array) when ``p`` does not perturb the lidar."""
    if not lidar_active(p):
        return ranges
    from racecav.common.config import SensorConfig

    r = np.array(ranges, dtype=np.float64)
    hit = np.isfinite(r)
    if p.range_noise_m or p.range_noise_rel:
        sigma = np.sqrt(p.range_noise_m ** 2 + (p.range_noise_rel * np.where(hit, r, 0.0)) ** 2)
        r = np.where(hit, r + sigma * rng.standard_normal(r.shape), r)
    # The car's sensor also has samples just outside the sector (preprocess keeps a margin), so
    # its edge rays have two neighbours: one virtual sample beyond each edge, the edge ray's own
    # return (dropped as often as any), stands in for them.
    r = np.concatenate([r[..., :1], r, r[..., -1:]], axis=-1)
    if p.dropout:
        r[rng.random(r.shape) < p.dropout] = np.inf
    ok = np.isfinite(r) & (r >= spec.range_min) & (r <= spec.range_max)
    ray = ray_angles(spec).astype(np.float64)
    th = np.concatenate([[ray[0] - spec.angle_increment], ray, [ray[-1] + spec.angle_increment]])
    gap = SensorConfig().max_gap_deg
    flat, okf = r.reshape(-1, r.shape[-1]), ok.reshape(-1, r.shape[-1])
    out = np.stack([fill_holes(th, flat[i], okf[i], gap) for i in range(flat.shape[0])])
    out = out[:, 1:-1].reshape(np.shape(ranges))
    return scan_ranges(out, np.isfinite(out), spec)


def command_delay(p: PerturbConfig, rng: np.random.Generator, size=None):
    """Seconds after its own compute time at which a command takes effect: latency + actuator
    delay + the scan's jitter (uniform in [0, scan_jitter_s], one draw per scan)."""
    jitter = rng.uniform(0.0, p.scan_jitter_s, size) if p.scan_jitter_s else (0.0 if size is None else np.zeros(size))
    return p.latency_s + p.actuator_delay_s + jitter
