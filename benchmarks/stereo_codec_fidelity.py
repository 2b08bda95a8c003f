"""What each image codec does to zoo:stereo's answers (d_coll, the disparity map) on rendered
frames and the Motorcycle pair, and whether the default fidelity bound admits it
(`experiments.nav_fidelity`; `elasticfog bench nav --json` carries the same rows).

    python benchmarks/stereo_codec_fidelity.py [--size 320x240]... [--frames 8] [--json]
"""

from __future__ import annotations

import argparse
import json

from experiments.nav_fidelity import markdown, measure, summary


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", action="append", help="WxH (repeatable; default 320x240)")
    parser.add_argument("--frames", type=int, default=8, help="rendered frames per size")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    rows = []
    for size in args.size or ["320x240"]:
        width, height = (int(v) for v in size.split("x"))
        rows += measure(width, height, args.frames)
    table = summary(rows)
    print(json.dumps(table) if args.json else markdown(table))


if __name__ == "__main__":
    main()
