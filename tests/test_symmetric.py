"""The mirror-symmetric actor (training/symmetric.py, ``--mirror-symmetric``)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from racecav.training.mirror import MirroredPolicy, mirror_scans
from racecav.training.symmetric import mirror_index, pair_swap
from tests.checkpoints_support import ROW16


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


def test_dagger_fits_a_symmetric_actor_to_the_mirror_teacher(tmp_path):
    """``train dagger --mirror-symmetric``: the actor stays tied through the imitation's own
    optimizer, on symmetric (frozen) statistics, so its export is its own mirror image."""
    import shutil

    from racecav.cli import main
    from racecav.common.scenario import SCENARIOS_DIR
    from racecav.training.select import checkpoint_policy

    crossings = tmp_path / "scenarios"
    crossings.mkdir()
    shutil.copy(SCENARIOS_DIR / "left-to-right.toml", crossings)
    run = tmp_path / "d"
    assert main(["train", "dagger", "--run-dir", str(run), "--preset", "fast", "--mirror-symmetric",
                 "--expert", "mirror", "--mirror-families", "left-to-right", "--scenarios", str(crossings),
                 "--scenario-share", "1.0", "--n-envs", "8", "--n-steps", "16", "--batch-size", "64",
                 "--grad-steps", "5", "--checkpoint-every", "128", "--n-obstacles", "0", "--obs-stack", "2",
                 "--lidar", "wide", "--lr", "1e-3",
                 "--init-from", ROW16, "--steps", "256", "--no-progress"]) == 0
    pol = checkpoint_policy(run / "latest.zip")
    scans = np.random.default_rng(2).uniform(0.2, 12.0, (64, 2 * 169)).astype(np.float32)
    assert np.allclose(MirroredPolicy(pol)(scans), pol(scans), atol=1e-5)
    assert np.allclose(pol.obs_mean, mirror_scans(pol.obs_mean, 2), atol=1e-6)


@pytest.mark.parametrize("stage,flags,says", [
    ("overtake", ["--mirror-symmetric", "--mirror-augment"], "choose one"),
    ("dagger", ["--mirror-augment", "--init-from", "common/data/policies/avoid.zip"], "--mirror-augment"),
])
def test_mirror_flags_that_do_not_combine_are_refused(tmp_path, capsys, stage, flags, says):
    from racecav.cli import main

    assert main(["train", stage, "--run-dir", str(tmp_path / "r"), "--preset", "fast", *flags, "--steps", "64"]) == 2
    assert says in capsys.readouterr().out
