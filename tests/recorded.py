"""The recorded observations of the shipped-policy equality tests, in any policy's view.

tests/data/policy_obs.npz holds the paper's 170-ray scans; tests/data/policy_obs_wide.npz
holds common/lidar.WIDE_SCAN scans, which contain every view (both from
``training.select.record_observations``).
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
