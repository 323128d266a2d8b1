"""Sim-to-real perturbations: one model for both backends and the sim service.

Each perturbation acts where it happens on the car (settings: common/config.PerturbConfig;
presets with their sources: common/data/perturbations.toml, docs/robustness.md):

- the lidar (:func:`perturb_scan`, called by both worlds on the agent's scan): Gaussian range
  noise (absolute and range-proportional, in quadrature), dropped returns (the S2 reports 0; our
  Scan says +inf), then the sensor service's own hole filling (services/sensor/preprocess.py
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
import tomllib
from pathlib import Path

import numpy as np

from racecav.common.config import PerturbConfig
from racecav.common.lidar import LidarSpec, ray_angles, scan_ranges

PRESETS_FILE = Path(__file__).parent / "data" / "perturbations.toml"
SALT = 58
"""Mixed into the episode seed: the perturbation's draws never repeat the scenario's."""


def keys() -> list[str]:
    return list(PerturbConfig.model_fields)


def _check_keys(data: dict, where: str) -> None:
    for k in data:
        if k not in PerturbConfig.model_fields:
            raise ValueError(f"{where}: unknown key {k!r} (known: {', '.join(keys())})")


def load_presets(path: Path | str | None = None) -> dict[str, dict]:
    """Preset name -> its non-default fields, validated; ValueError naming file, preset and key."""
    path = Path(path or PRESETS_FILE)
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"perturbation presets {path}: {e}") from None
    out = {}
    for name, table in data.items():
        if not isinstance(table, dict):
            raise ValueError(f"perturbation presets {path}: {name!r} is not a [preset] table")
        _check_keys(table, f"perturbation presets {path} [{name}]")
        try:
            PerturbConfig.model_validate(table)
        except Exception as e:  # a value out of its range: one line
            raise ValueError(f"perturbation presets {path} [{name}]: {str(e).splitlines()[-2].strip()}") from None
        out[name] = dict(table)
    return out


def parse_text(text: str, presets: dict[str, dict] | None = None) -> dict:
    """``"PRESET"``, ``"key=value,..."`` or both (later items win) -> PerturbConfig fields.

    :raises ValueError: one line naming the unknown preset or key, or the bad value.
    """
    presets = load_presets() if presets is None else presets
    out: dict = {}
    for item in filter(None, (x.strip() for x in text.split(","))):
        key, eq, value = item.partition("=")
        key = key.strip()
        if not eq:
            if key == "nominal":
                continue
            if key not in presets:
                raise ValueError(f"perturb: unknown preset {key!r} (known: nominal, {', '.join(presets)}; "
                                 f"or key=value with keys {', '.join(keys())})")
            out.update(presets[key])
            continue
        _check_keys({key: 0}, "perturb")
        try:
            out[key] = float(value)
        except ValueError:
            raise ValueError(f"perturb: {key}={value.strip()!r} is not a number") from None
    return out


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
    from racecav.services.sensor.preprocess import fill_holes

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


def draw(p: PerturbConfig, rng: np.random.Generator) -> PerturbConfig:
    """One randomised perturbation for training: every field between the ideal value and ``p``'s
    (uniform; offsets of either sign)."""
    out = {}
    for k, v in p.active().items():
        ideal = PerturbConfig.model_fields[k].default
        u = rng.uniform(0.0, 1.0)
        if k in ("mount_yaw_rad", "steer_offset_rad"):
            u = rng.uniform(-1.0, 1.0)
        out[k] = ideal + u * (v - ideal)
    return PerturbConfig.model_validate(out)
