"""The recorded observations of the shipped-policy equality tests, in any policy's view.

tests/data/policy_obs.npz holds the paper's 170-ray scans; tests/data/policy_obs_wide.npz
holds common/lidar.WIDE_SCAN scans, which contain every view (both from
``record_observations`` below, which drives with noise: a data generator, not a trial loop).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from racecav.common.lidar import VIEWS, WIDE_SCAN, LidarSpec, view_index

DATA = Path(__file__).resolve().parent / "data"


def recorded_obs(view: LidarSpec | None = None) -> np.ndarray:
    """Sanitised observations (float32, (n, view.n_rays)) of the view (default: the paper's)."""
    view = view or VIEWS["paper"]
    if view == VIEWS["paper"]:
        return np.load(DATA / "policy_obs.npz")["obs"]
    return np.load(DATA / "policy_obs_wide.npz")["obs"][:, view_index(WIDE_SCAN, view)]


def record_observations(path: Path, seed: int = 7, scan: str = "paper") -> Path:
    """Record real observations for the SB3-vs-numpy equality test (tests/data/policy_obs.npz):
    fast-world scans with traffic (both headings, racing policy driving) and PyBullet
    intersection scans, including near-contact ones.

    ``scan="wide"``: common/lidar.WIDE_SCAN, which holds every view (tests/data/policy_obs_wide.npz,
    for policies trained on a wider view): PyBullet only (the racetrack with traffic, the paper's
    and the conflict-timed scenarios), the racing policy driving on the paper's rays of it.
    """
    import numpy as np

    from racecav.common.lidar import WIDE_SCAN, view_index
    from racecav.common.policy import load_policy
    from racecav.sim.bullet_world import BulletWorld
    from racecav.common.registry import CONFLICT_SCENARIOS, PAPER_SCENARIOS as SCENARIOS
    from racecav.training.vec_env import FastVecEnv

    pol = load_policy("racing")
    rng = np.random.default_rng(seed)
    out = []
    if scan == "paper":
        for heading in ("default", "reversed"):
            env = FastVecEnv(n_envs=16, heading=heading, n_obstacles=15, driver="policy:racing", seed=seed)
            obs = env.reset()
            for k in range(60):
                a = pol(obs)
                a[:, 1] += rng.normal(0, 0.3, len(a))  # some off-policy wandering: walls up close
                obs, *_ = env.step(np.clip(a, -1, 1))
                if k % 20 == 19:
                    out.append(obs.copy())
    lidar = None if scan == "paper" else WIDE_SCAN
    paper = slice(None) if lidar is None else view_index(WIDE_SCAN, pol.lidar)
    scenarios = SCENARIOS if scan == "paper" else ("racetrack", *SCENARIOS, *CONFLICT_SCENARIOS)
    for sc in scenarios:
        bw = BulletWorld(sc, lidar=lidar, seed=seed)
        obs = bw.reset(seed=seed)
        for k in range(40 if sc != "racetrack" else 120):
            a = pol(obs[0][paper])
            if lidar is not None:
                a[1] = np.clip(a[1] + rng.normal(0, 0.3), -1, 1)
            obs, _, col, _ = bw.step(a)
            if k % 5 == 0:
                out.append(obs.copy())
            if col[0]:
                break
        bw.close()
    arr = np.concatenate(out).astype(np.float32)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, obs=arr)
    return path
