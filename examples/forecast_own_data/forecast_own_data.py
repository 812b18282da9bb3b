"""Forecast trajectories of a data set of your own, added by YAML (constant velocity and the GP, ADE/FDE).

The forecasting task (``task=ethucy_forecast``) runs on any data set of ``task.datasets``: observe 8 steps
of every pedestrian of a 20-step window, predict the next 12, and score the prediction by the average
(ADE) and final (FDE) displacement error in metres. The ETH/UCY scenes are data sets described by YAML
(``conf/dataset/*.yaml`` in the package); yours join the same way, from a config folder of your own
(``conf/dataset/plaza_a.yaml`` and ``plaza_b.yaml`` beside this script) through Hydra's search path.

This script writes two small synthetic scenes in the ETH/UCY text format (``frame ped x y``, one line per
pedestrian and frame, frames 10 apart, 0.4 s per row) into a temporary folder: pedestrians walk at
1.2 m/s on circles (turning 0.3 rad/s, left or right). It trains the GP on ``plaza_a`` and tests both
predictors on the held-out ``plaza_b``. On circles the constant-velocity error has a closed form (every
pedestrian the same, up to a rotation and a mirror image), printed beside the table; the GP, which learns
``[v_t, v_{t-1}] -> v_{t+1}`` from plaza_a, should beat it. To keep the run short the GP's kernel
hyperparameters are set (``task.gp.lengthscale``, ``outputscale``, ``noise_std``: the data are exact, so a
small noise) rather than fitted (``task.gp.fit_iters=0``); ``--fit-iters 40`` fits them by marginal likelihood
(slower, and on these exact circles no better).

Run:  python forecast_own_data.py            (about 10 s)
The same from the command line (after writing the files): see examples/README.md.
"""

from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
CONF = HERE / "conf"            # this example's config folder (dataset/plaza_a.yaml, dataset/plaza_b.yaml)

SPEED, TURN, DT = 1.2, 0.3, 0.4   # m/s, rad/s, s per row
OBS, PRED = 8, 12                 # the benchmark's observed and predicted steps


def write_scene(path: Path, seed: int, num_peds: int = 40, life: int = 30, spread: int = 3) -> None:
    """A scene in the ETH/UCY format: pedestrian i appears at row step ``spread * i`` and walks ``life``
    steps on a circle of radius SPEED / TURN (turning left or right), from a random point and heading."""
    rng = np.random.default_rng(seed)
    rows = []
    r, th = SPEED / TURN, TURN * DT                     # radius (m), turn per row step (rad)
    for ped in range(num_peds):
        start = spread * ped
        p0, heading, side = rng.uniform(0.0, 30.0, 2), rng.uniform(-math.pi, math.pi), rng.choice([-1.0, 1.0])
        # centre of the circle: to the left (side = +1) or right of the heading
        centre = p0 + r * side * np.array([-math.sin(heading), math.cos(heading)])
        phi0 = math.atan2(*(p0 - centre)[::-1])
        for j in range(life):
            phi = phi0 + side * j * th
            x, y = centre + r * np.array([math.cos(phi), math.sin(phi)])
            rows.append((10 * (start + j), ped + 1, x, y))
    rows.sort(key=lambda t: (t[0], t[1]))             # the format: frames in order
    path.write_text("".join(f"{f}\t{p}\t{x:.9f}\t{y:.9f}\n" for f, p, x, y in rows))


def cv_closed_form() -> tuple[float, float]:
    """ADE and FDE of constant velocity (the last observed displacement carried forward) on such a circle:
    in the frame of the last observed point, e_k = r |(cos k th - 1 - k (1 - cos th), sin k th - k sin th)|."""
    r, th = SPEED / TURN, TURN * DT
    e = [r * math.hypot(math.cos(k * th) - 1 - k * (1 - math.cos(th)), math.sin(k * th) - k * math.sin(th))
         for k in range(1, PRED + 1)]
    return sum(e) / len(e), e[-1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gp-points", type=int, default=600, help="GP data budget (task.gp.points)")
    ap.add_argument("--fit-iters", type=int, default=0, help="marginal-likelihood steps (task.gp.fit_iters)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    from dslearn import api

    with tempfile.TemporaryDirectory() as tmp:          # nothing is written anywhere else
        write_scene(Path(tmp) / "plaza_a.txt", seed=1)
        write_scene(Path(tmp) / "plaza_b.txt", seed=2)
        df = api.run(
            "task=ethucy_forecast",
            f"hydra.searchpath=['file://{CONF}']",      # where conf/dataset/plaza_*.yaml are found
            "+dataset@task.datasets.plaza_a=plaza_a",   # compose the YAMLs into the task's data sets
            "+dataset@task.datasets.plaza_b=plaza_b",
            f"task.data_root='{tmp}'",                  # their files' folder (root: null in the YAMLs)
            "task.scenes=[plaza_b]",                    # held-out test scene ...
            "task.train_scenes=[plaza_a]",              # ... trained on plaza_a (not in the ETH/UCY folds)
            "task.predictors=[cv,gp]",
            f"task.gp.points={args.gp_points}",
            f"task.gp.fit_iters={args.fit_iters}",
            "task.gp.noise_std=0.05",                   # m/s: exact data (the default 0.3 is for real tracks)
            f"seed={args.seed}",
        )
    table = df[df.metric.isin(["ade", "fde", "count"])].pivot_table(index="model", columns="metric", values="value")
    table = table.loc[["cv", "gp"], ["ade", "fde", "count"]]
    table["count"] = table["count"].astype(int)           # pedestrian-windows scored
    print("Forecast on plaza_b (trained on plaza_a), 8 -> 12 steps, metres:")
    print(table.to_string(float_format=lambda v: f"{v:.6f}"))
    ade, fde = cv_closed_form()
    print(f"cv closed form: ade {ade:.6f} fde {fde:.6f}")
    # by construction: constant velocity's error is the closed form's (the data are exact circles)
    assert math.isclose(table.loc["cv", "ade"], ade, abs_tol=1e-6), (table.loc["cv", "ade"], ade)
    assert math.isclose(table.loc["cv", "fde"], fde, abs_tol=1e-6), (table.loc["cv", "fde"], fde)


if __name__ == "__main__":
    main()
