#!/usr/bin/env python3
"""Where a run's training episodes end, per million frames (issue 43, docs/strong.md).

usage: python3 tools/score_bins.py METRICS.csv [METRICS.csv ...]

For each run's `metrics.csv` (written by `invaders train`; its snapshots keep a copy) and each
million emulator frames with at least 20 episodes: the number of episodes, their mean return,
and the share of episodes that scored below 500, 500 to 649, 650 or more, and 1 000 or more.
The first wave's 36 invaders are worth 630 points (six rows of 30, 25, 20, 15, 10 and 5), so
the 500-649 bin holds the games that ended about the end of the first wave.
"""

import csv
import sys

BINS = [
    ("below 500", lambda r: r < 500),
    ("500-649", lambda r: 500 <= r < 650),
    ("650 or more", lambda r: r >= 650),
    ("1 000 or more", lambda r: r >= 1000),
]


def main(paths):
    if not paths:
        sys.exit(__doc__.strip().splitlines()[2])
    for path in paths:
        try:
            with open(path, newline="") as f:
                rows = [(int(r["emulator_frames"]), float(r["reward"])) for r in csv.DictReader(f)]
        except (OSError, KeyError, ValueError, TypeError) as e:
            sys.exit(f"cannot read {path} as a run's metrics.csv: {e!r}")
        print(path)
        print("| frames | episodes | mean | " + " | ".join(name for name, _ in BINS) + " |")
        print("| --- " * (3 + len(BINS)) + "|")
        last = max((frames for frames, _ in rows), default=0)
        for m in range(1, last // 1_000_000 + 2):
            w = [r for frames, r in rows if (m - 1) * 1_000_000 < frames <= m * 1_000_000]
            if len(w) < 20:
                continue
            shares = [f"{100 * sum(map(test, w)) / len(w):.0f}%" for _, test in BINS]
            print(f"| {m - 1}-{m} M | {len(w)} | {sum(w) / len(w):.0f} | " + " | ".join(shares) + " |")


if __name__ == "__main__":
    main(sys.argv[1:])
