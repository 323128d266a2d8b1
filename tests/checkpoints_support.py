"""Committed checkpoints that tests train from or drive with, when the test needs a particular
policy rather than whatever is shipped as avoid today."""

# Row 16 at 4 M (avoid-papertimed-lowlr, shipped as avoid 2026-12-01 to 02): plain Gaussian
# noise (the shipped row 31 explores with gSDE, which a plain-noise run cannot start from
# without --init-std), a 2-scan stack on the wide view, and the policy rows 22 and the timing
# probe were measured with.
ROW16 = "training/checkpoints/avoid-papertimed-lowlr/checkpoints/step_004005888.zip"
