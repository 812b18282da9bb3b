"""Put a motion model of your own into the comparison matrix, beside the built-in constant velocity.

Three files make a part: the class (``my_models.py``: a :class:`dslearn.models.base.MotionModel`), a YAML
that names it (``conf/model/damped_cv.yaml``: the option ``model=damped_cv``) and Hydra's search path,
which joins this example's ``conf`` folder to the package's. A matrix cell (``task=matrix``) is a method
on a scenario; the method preset ``ekf_lin_hybrid`` is Yu et al.'s distributed EKF with hybrid
consensus and the ``lin`` model, and ``model=damped_cv`` swaps the model part. The cell's rows are
``method, scenario, node, node_kind, episode, metric, value`` (``rmse`` and ``nees_pos``, position NEES / 2
per target, and ``runtime_s``); the table averages them over the test episodes and the sensing nodes.

The script checks the model first (its exact Jacobian against central finite differences), then runs
three cells on Yu's two-agent scenario: ``lin``, ``damped_cv`` and ``damped_cv`` with ``model.damping=0``,
which is the constant-velocity model written another way and must give lin's numbers.

Run:  python run_matrix.py              (about 10 s)
The same cell from the command line (from this folder):
      PYTHONPATH=. dslearn-run task=matrix method=ekf_lin_hybrid model=damped_cv scenario=yu_two_agents \\
          "hydra.searchpath=[file://$PWD/conf]" hydra.run.dir=<somewhere>
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))   # the YAML's _target_ (my_models....) is imported from this folder
CONF = HERE / "conf"

from my_models import DampedConstantVelocity  # noqa: E402

from dslearn.types import StepContext  # noqa: E402


def jacobian_error(model: DampedConstantVelocity, dt: float, seed: int = 0) -> float:
    """Largest difference between the model's Jacobian and central finite differences of its mean, at random
    states (float64; the velocities include slow ones, where v / |v| bends most)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(8, model.state_dim, generator=g, dtype=torch.float64)
    x[:2] *= 0.2                                         # slow: where v / |v| bends most
    ctx, h = StepContext(dt=dt), 1e-6
    f = model.jacobian(x, ctx)
    cols = []
    for j in range(model.state_dim):
        e = torch.zeros(model.state_dim, dtype=torch.float64)
        e[j] = h
        cols.append((model(x + e, ctx) - model(x - e, ctx)) / (2 * h))
    fd = torch.stack(cols, dim=-1)                       # (B, Dx, Dx): column j = d f / d x_j
    return float((f - fd).abs().max())


def cell(*overrides: str, test_episodes: int, seed: int):
    """One matrix cell: mean RMSE and NEES over the test episodes and sensing nodes, and the method's label."""
    from dslearn import api

    df = api.run("task=matrix", "method=ekf_lin_hybrid", "scenario=yu_two_agents",
                 f"hydra.searchpath=['file://{CONF}']",   # where model/damped_cv.yaml is found
                 "task.train_episodes=0",                 # neither model learns
                 f"task.test_episodes={test_episodes}", f"seed={seed}", *overrides)
    sensing = df[df.node_kind == "sensor"].groupby("metric")["value"].mean()
    return df.method.iloc[0], sensing["rmse"], sensing["nees_pos"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--test-episodes", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    err = jacobian_error(DampedConstantVelocity(num_agents=2, damping=0.5, speed=1.4), dt=0.25)
    print(f"jacobian vs finite differences: max abs error {err:.2e}")
    assert err < 1e-7, err

    rows = [
        ("lin", *cell(test_episodes=args.test_episodes, seed=args.seed)),
        ("damped_cv", *cell("model=damped_cv", test_episodes=args.test_episodes, seed=args.seed)),
        ("damped_cv k=0", *cell("model=damped_cv", "model.damping=0", test_episodes=args.test_episodes,
                                seed=args.seed)),
    ]
    print(f"Yu's two-agent scenario, {args.test_episodes} test episodes, seed {args.seed}:")
    print(f"{'model':<14} {'method':<24} {'rmse_m':>10} {'nees_pos':>10}")
    for name, label, rmse, nees in rows:
        print(f"{name:<14} {label:<24} {rmse:>10.6f} {nees:>10.6f}")
    # by construction: with damping 0 the model is constant velocity, so the cell is lin's
    assert math.isclose(rows[2][2], rows[0][2], rel_tol=1e-9) and math.isclose(rows[2][3], rows[0][3], rel_tol=1e-9)


if __name__ == "__main__":
    main()
