"""Recorded d_coll frames the navigation tests share."""

from __future__ import annotations

# d_coll of frame 34 of `python benchmarks/nav_offcentre.py --size 640x480 --half-width 0`
# (straight at the off-centre box, lap 0, the axle 0.48 m from its face), the model's 41 bins
# over K = −2..2 1/m: the path's bin (K = 0, index 20) saw nothing (5 m, the maximum range).
OFFCENTRE_640_FRAME34 = [5.0] * 5 + [
    0.52, 0.51, 0.51, 0.48, 0.51, 0.5, 0.46, 0.47, 0.49, 0.42, 0.42, 0.47, 0.49, 0.43, 0.45,
    5.0, 0.44, 0.44, 0.48, 0.4, 0.42, 0.47,
] + [5.0] * 14  # fmt: skip
