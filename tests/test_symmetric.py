"""The mirror-symmetric actor (training/symmetric.py, ``--mirror-symmetric``)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from racecav.training.mirror import MirroredPolicy, mirror_scans
from racecav.training.symmetric import mirror_index, pair_swap


def test_permutations_are_involutions():
    m = mirror_index(10, 2)
    assert m.tolist() == [4, 3, 2, 1, 0, 9, 8, 7, 6, 5]
    assert np.array_equal(m[m], np.arange(10))
    assert pair_swap(6).tolist() == [1, 0, 3, 2, 5, 4]
    with pytest.raises(ValueError, match="obs_stack 3"):
        mirror_index(10, 3)
    with pytest.raises(ValueError, match="no pairs"):
        pair_swap(5)


def test_symmetric_run_trains_resumes_and_exports_an_exactly_symmetric_policy(tmp_path):
    """A short PPO run with --mirror-symmetric: after PPO's updates (and on resume) the exported
    policy (the plain numpy path, with the run's normalisation) is its own mirror image, and
    the same run without the flag is not."""
    from racecav.cli import main
    from racecav.training.select import checkpoint_policy

    flags = ["--preset", "fast", "--n-envs", "8", "--n-steps", "16", "--batch-size", "64", "--n-epochs", "2",
             "--checkpoint-every", "128", "--n-obstacles", "2", "--driver", "centerline", "--world", "figure8", "--obs-stack", "2",
             "--lidar", "wide", "--no-progress"]
    sym, plain = tmp_path / "sym", tmp_path / "plain"
    assert main(["train", "overtake", "--run-dir", str(sym), "--steps", "128", "--mirror-symmetric", *flags]) == 0
    assert main(["train", "overtake", "--run-dir", str(sym), "--steps", "256", "--resume", "--no-progress"]) == 0
    assert json.loads((sym / "config.json").read_text())["mirror_symmetric"] is True
    assert main(["train", "overtake", "--run-dir", str(plain), "--steps", "128", *flags]) == 0
    scans = np.random.default_rng(1).uniform(0.2, 12.0, (64, 2 * 169)).astype(np.float32)
    for run, symmetric in ((sym, True), (plain, False)):
        ck = sorted((run / "checkpoints").glob("step_*.zip"))[-1]
        pol = checkpoint_policy(ck)
        assert pol.normalize
        same = np.allclose(MirroredPolicy(pol)(scans), pol(scans), atol=1e-5)
        assert same == symmetric, run
        if symmetric:  # the statistics are symmetric too, not only the weights
            assert np.allclose(pol.obs_mean, mirror_scans(pol.obs_mean, 2), atol=1e-6)


def test_dagger_refuses_the_symmetric_actor(tmp_path, capsys):
    from racecav.cli import main

    assert main(["train", "dagger", "--run-dir", str(tmp_path / "d"), "--preset", "fast", "--mirror-symmetric",
                 "--init-from", "common/data/policies/avoid.zip", "--steps", "64"]) == 2
    assert "--mirror-symmetric" in capsys.readouterr().out
