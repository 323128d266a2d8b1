"""Checkpoints that tests train from or drive with, when the test needs a particular policy rather
than whatever is shipped as avoid today (moved from training/checkpoints/, with the run's
config.json that holds their view settings)."""

from pathlib import Path

DATA = Path(__file__).resolve().parent / "data" / "checkpoints"
# Row 16 at 4 M (avoid-papertimed-lowlr, shipped as avoid 2026-12-01 to 02): plain Gaussian
# noise, a 2-scan stack on the wide view.
ROW16 = str(DATA / "avoid-papertimed-lowlr" / "checkpoints" / "step_004005888.zip")
# Row 31 at 5 M (avoid-gsde-flow120, the avoid shipped from 2026-12-02 to 12-05): gSDE, two
# consecutive wide scans, no brake; the frozen policy the teacher tests relabel.
ROW31 = str(DATA / "avoid-gsde-flow120" / "checkpoints" / "step_005005312.zip")
