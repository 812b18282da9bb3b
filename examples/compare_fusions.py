"""Compare fusion strategies on Yu et al.'s scenario from Python: one motion model, five ways to fuse.

Two pedestrians cross an 8 x 8 m area, watched by 4 range-limited position sensors that talk to 6
communication nodes over a radio graph (Yu et al., Section V-A). Every node runs an information-form
EKF; what differs is what a node fuses:

* ``individual``  - only its own measurements (no communication),
* ``cm``          - consensus on measurements (L rounds on the novel information),
* ``ci``          - consensus on information (L rounds on the posterior),
* ``hybrid``      - Yu et al.'s hybrid CMCI (prior and novel information; with omega = 1 it equals CI,
                    since averaging is linear: the table shows it),
* ``centralized`` - the reference: every node receives every measurement.

``dslearn.api.yu_study`` composes the same configuration as ``dslearn-run task=yu model=.. consensus=..``
(defaults, validation) and returns the study; ``.run()`` returns tidy rows (node x episode x metric).
The table is the tracking RMSE (``track_rmse``, metres) and the NEES (divided by the state dimension,
1 for a consistent filter), averaged over the test episodes and the sensing nodes (Yu's "sensor average").

Run:  python compare_fusions.py                       (the constant-velocity model, about 10 s)
      python compare_fusions.py --model gp_increment --train-episodes 10   (the online GP; slower)
"""

from __future__ import annotations

import argparse
import math
import time

FUSIONS = ("individual", "cm", "ci", "hybrid", "centralized")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="lin", help="a conf/model option: lin, sfm, gp, gp_increment, ...")
    ap.add_argument("--train-episodes", type=int, default=2, help="episodes the learning models learn on")
    ap.add_argument("--test-episodes", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    from dslearn import api

    rows = []
    for fusion in FUSIONS:
        t0 = time.perf_counter()
        study = api.yu_study(model=args.model, consensus=fusion, train_episodes=args.train_episodes,
                             test_episodes=args.test_episodes, seed=args.seed)
        df = study.run()                                 # columns ... node, node_kind, episode, metric, value
        sensing = df[df.node_kind == "sensor"]           # Yu's table averages over the sensing nodes
        mean = sensing.groupby("metric")["value"].mean()
        rows.append((fusion, mean["track_rmse"], mean["nees"], time.perf_counter() - t0))

    print(f"model {args.model}: {args.train_episodes} training / {args.test_episodes} test episodes, seed {args.seed}")
    print(f"{'fusion':<12} {'rmse_m':>10} {'nees':>10} {'seconds':>8}")
    for fusion, rmse, nees, secs in rows:
        print(f"{fusion:<12} {rmse:>10.6f} {nees:>10.6f} {secs:>8.1f}")

    by = {r[0]: r[1] for r in rows}
    assert all(math.isfinite(v) for v in by.values())
    # hybrid with omega = 1 is CI: the consensus rounds average (prior + novel) linearly either way
    assert math.isclose(by["hybrid"], by["ci"], rel_tol=1e-9), (by["hybrid"], by["ci"])
    print(f"centralized / individual rmse: {by['centralized'] / by['individual']:.3f}")


if __name__ == "__main__":
    main()
