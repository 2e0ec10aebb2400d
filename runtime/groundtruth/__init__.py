"""Light transport for ground truth and baselines: light environments (point lights, HDR maps, median
cut), exact visibility ray casts, and the baselines the evaluation measures against.

Only the synthetic camera, training and evaluation use this package; no per-frame stage may import it
(``tests/test_layering.py`` enforces that)."""
