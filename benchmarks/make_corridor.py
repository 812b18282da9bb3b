"""The shipped "corridor" data set (``dslearn/data/corridor/corridor.txt``): synthetic pedestrians in the
ETH/UCY text format, the example data set of ``conf/scenario/corridor.yaml`` (the template for adding a data
set by YAML).

Pairs of pedestrians walk side by side along a corridor of ``LENGTH`` x ``WIDTH`` metres, one pair entering
every ``GAP`` rows, alternately from the left end (in the lower lane) and from the right end (in the upper
lane), so two pairs are in the corridor at a time and pass each other. Each pair has its own walking speed
(uniform in ``SPEED``); a pedestrian's speed along the corridor and its lateral velocity are Ornstein-Uhlenbeck
processes around the pair's speed and zero, and the partners walk ``SEPARATION`` metres apart across the
corridor. A pedestrian has one row every 10 video frames at 25 fps (0.4 s) while it is inside the corridor;
positions are rounded to centimetres, like the ETH/UCY files. Everything is drawn from ``--seed``
(``numpy.random.default_rng``), so the file is reproducible::

    python benchmarks/make_corridor.py            # (re)write the file (seed 0)
    python benchmarks/make_corridor.py --check    # exit 1 if the shipped file differs from what it would write

Format (``dslearn.data.ethucy.read_trajectories``): one line per observation, four tab-separated numbers
``frame ped x y`` (frame and pedestrian id written as ``780.0``, positions in metres), frames non-decreasing,
every frame a multiple of 10.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "dslearn" / "data" / "corridor" / "corridor.txt"

FRAME_STEP = 10  # video frames between a pedestrian's rows
FPS = 25.0  # video frame rate: a row step is FRAME_STEP / FPS = 0.4 s
LENGTH, WIDTH = 16.0, 4.0  # corridor [m]: x in [0, LENGTH], y in [0, WIDTH]
LANES = (1.2, 2.8)  # lane centres [m]: left-to-right pairs walk in the lower lane, right-to-left in the upper
PAIRS = 10  # pairs of pedestrians
GAP = 20  # rows between the entries of consecutive pairs
SPEED = (1.0, 1.4)  # walking speed of a pair [m/s], uniform
SEPARATION = (0.6, 0.8)  # the partners' distance across the corridor [m], uniform
SPEED_STD = 0.05  # stationary std of a pedestrian's speed around the pair's [m/s]
LATERAL_STD = 0.05  # stationary std of the lateral velocity [m/s]
CORRELATION = 0.8  # OU correlation per row step of both velocities


def trajectories(seed: int = 0) -> list[tuple[int, int, float, float]]:
    """``(frame, ped, x, y)`` rows of the corridor, sorted by frame then pedestrian (positions unrounded)."""
    rng = np.random.default_rng(seed)
    dt = FRAME_STEP / FPS
    rows = []
    innov = np.sqrt(1.0 - CORRELATION ** 2)
    for j in range(PAIRS):
        direction = 1.0 if j % 2 == 0 else -1.0
        lane = LANES[0] if direction > 0 else LANES[1]
        speed = rng.uniform(*SPEED)
        sep = rng.uniform(*SEPARATION)
        start = j * GAP
        for side in (-0.5, 0.5):
            ped = 2 * j + (1 if side < 0 else 2)
            x = (0.0 if direction > 0 else LENGTH) - direction * rng.uniform(0.0, 0.3)  # just outside the entry
            y = lane + side * sep
            vx = speed + SPEED_STD * rng.standard_normal()
            vy = LATERAL_STD * rng.standard_normal()
            k = 0
            while True:
                if 0.0 <= x <= LENGTH:
                    rows.append(((start + k) * FRAME_STEP, ped, x, y))
                elif k > 0 and (x - LENGTH / 2) * direction > 0:  # left through the far end
                    break
                vx = speed + CORRELATION * (vx - speed) + innov * SPEED_STD * rng.standard_normal()
                vy = CORRELATION * vy + innov * LATERAL_STD * rng.standard_normal()
                x += direction * vx * dt
                y = float(np.clip(y + vy * dt, 0.1, WIDTH - 0.1))
                k += 1
    rows.sort(key=lambda r: (r[0], r[1]))
    return rows


def text(seed: int = 0) -> str:
    """The file's text: ``frame<TAB>ped<TAB>x<TAB>y`` lines, positions rounded to centimetres."""
    return "".join(f"{float(f):.1f}\t{float(p):.1f}\t{x:.2f}\t{y:.2f}\n" for f, p, x, y in trajectories(seed))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--check", action="store_true", help="exit 1 if the file differs from what would be written")
    a = ap.parse_args(argv)
    new = text(a.seed)
    if a.check:
        same = a.out.is_file() and a.out.read_text() == new
        print(f"{a.out}: {'up to date' if same else 'differs from the generator output'}")
        return 0 if same else 1
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(new)
    print(f"wrote {a.out} ({new.count(chr(10))} lines, seed {a.seed})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
