"""Hand-set numbers vs "train each node alone, then freeze and run consensus" vs "train end to end through the
consensus", on held-out episodes of Yu et al.'s scenario and of a recorded scene (the LIN hybrid filter).

    python experiments/backprop/compare.py                      # yu_two_agents and eth_zara1, 20 + 20 episodes
    python experiments/backprop/compare.py --scenarios yu_two_agents --train 10 --test 10 --out cmp
    python experiments/backprop/compare.py --family gp          # the increment GP's hyperparameters (or lstm)

Each variant is a matrix cell (``dslearn-run task=matrix method=... scenario=...``) with the same seed, hence
the same training and test episodes; the tracking RMSE and NEES are the cell's own rows (sensor average over
the test episodes), the prediction error rolls the variant's motion model (hand-set or learned transition
matrix, the GP with its learned hyperparameters, the fine-tuned LSTM) out from every test episode's true initial state (Yu et al. Table II's protocol,
:func:`dslearn.metrics.tracking.prediction_error`). Writes ``compare.csv`` (one row per scenario and variant)
and ``compare.md`` into ``--out`` (default: a new ``backprop-compare/<date>_<time>``) and prints the table.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import pandas as pd
import torch

#: variant -> the overrides on top of ``task=matrix scenario=<s>`` (``--family lin``: the LIN hybrid filter)
VARIANTS = {
    "hand-set": ["method=ekf_lin_hybrid"],
    "nodes alone, frozen [q,r]": ["method=ekf_lin_hybrid_backprop", "learner.train_fusion=individual",
                                   "learner.learn=[q,r]"],
    "end to end [q,r]": ["method=ekf_lin_hybrid_backprop", "learner.learn=[q,r]"],
    "end to end [q,r,weights,omega]": ["method=ekf_lin_hybrid_backprop", "learner.learn=[q,r,weights,omega]"],
    "nodes alone, frozen [q,r,model]": ["method=ekf_lin_hybrid_backprop", "learner.train_fusion=individual",
                                         "learner.learn=[q,r,model]"],
    "end to end [q,r,model]": ["method=ekf_lin_hybrid_backprop", "learner.learn=[q,r,model]"],
}
_GP = ["method=ekf_gp_hybrid", "learner=backprop"]
_LSTM = ["method=ekf_lstm_hybrid", "learner=backprop", "learner.model_lr=1e-4"]
#: ``--family`` -> its variants: the model's own learner (online GP, offline LSTM), then learner=backprop
FAMILIES = {
    "lin": VARIANTS,
    "gp": {
        "online GP (hand-set hyperparameters)": ["method=ekf_gp_hybrid"],
        "nodes alone, frozen [model,r]": [*_GP, "learner.train_fusion=individual", "learner.learn=[model,r]"],
        "end to end [r,weights,omega]": [*_GP, "learner.learn=[r,weights,omega]"],
        "end to end [model,r]": [*_GP, "learner.learn=[model,r]"],
        "end to end [model,r,weights,omega]": [*_GP, "learner.learn=[model,r,weights,omega]"],
    },
    "lstm": {
        "offline LSTM": ["method=ekf_lstm_hybrid"],
        "nodes alone, frozen [model,q,r]": [*_LSTM, "learner.train_fusion=individual", "learner.learn=[model,q,r]"],
        "end to end [q,r,weights,omega]": [*_LSTM, "learner.learn=[q,r,weights,omega]"],
        "end to end [model,q,r]": [*_LSTM, "learner.learn=[model,q,r]"],
        "end to end [model,q,r,weights,omega]": [*_LSTM, "learner.learn=[model,q,r,weights,omega]"],
    },
}


def run_variant(scenario: str, overrides: list[str], train: int, test: int, seed: int) -> dict:
    from dslearn import api
    from dslearn.compose import build_study
    from dslearn.learning.backprop import LinearMotion
    from dslearn.metrics.tracking import prediction_error
    from dslearn.sim.scenario import sample_split
    from dslearn.types import AGENT_DIM

    cfg = api.compose("task=matrix", f"scenario={scenario}", f"task.train_episodes={train}",
                      f"task.test_episodes={test}", f"seed={seed}", *overrides)
    cell = build_study(cfg)
    t0 = time.perf_counter()
    df = cell.run()
    wall = time.perf_counter() - t0
    sensors = df[df["node_kind"] == "sensor"]
    per_ep = sensors.groupby(["metric", "episode"])["value"].mean()  # sensor average per episode
    out = {"scenario": scenario}
    for m in ("rmse", "nees_pos"):
        v = per_ep[m]
        out[m], out[f"{m}_std"] = float(v.mean()), float(v.std(ddof=1)) if len(v) > 1 else float("nan")
    # the motion model the variant tracked with: the hand-set constant velocity or the learned matrix
    method, scen = cell.method, cell.scenario
    ctx = scen.ctx()
    learned = getattr(method, "learned", None)
    per_node = False
    if "f_block" in (learned or {}) or (learned is None and hasattr(method.model, "matrix")):  # the LIN family
        f_block = (method.model.matrix(ctx.dt)[:AGENT_DIM, :AGENT_DIM] if learned is None
                   else torch.tensor(learned["f_block"], dtype=torch.float64))
        model = LinearMotion(method.model.num_agents, f_block.to(torch.float64), torch.zeros(4, 4, dtype=torch.float64))
    else:  # the model it tracked with: the learned one, or the model after its own learner
        model = getattr(method, "learned_model", method.model)
        per_node = bool(getattr(model, "learnable", False))  # a GP: one per node
    testeps, _ = sample_split(scen, cell.scenario_network, cell.seed, test, train, torch.float64, "cpu")
    nodes = cell.scenario_network.num_nodes if per_node else 1
    pe = prediction_error(model, testeps.states.to(torch.float64), nodes, ctx, per_node=per_node).mean(0)  # (B,)
    out["pred_err"], out["pred_err_std"] = float(pe.mean()), float(pe.std()) if len(pe) > 1 else float("nan")
    out["seconds"] = wall
    if learned is not None:
        out["q_diag"] = " ".join(f"{v:.3g}" for v in learned["q_diag"])
        r = learned["r"]
        out["r_diag"] = f"{r[0][0]:.3g} {r[1][1]:.3g}"
        out["omega"] = learned["omega"]
        out["s_per_epoch"] = learned["seconds_per_epoch"]
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenarios", default="yu_two_agents,eth_zara1", help="comma-separated (default: %(default)s)")
    p.add_argument("--train", type=int, default=20, help="training episodes (default: %(default)s)")
    p.add_argument("--test", type=int, default=20, help="held-out test episodes (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--family", default="lin", choices=sorted(FAMILIES),
                   help="the motion model whose numbers are learned (default: %(default)s)")
    p.add_argument("--out", default=None, help="output folder (default: a new backprop-compare/<date>_<time>)")
    a = p.parse_args(argv)
    out = Path(a.out or Path("backprop-compare") / time.strftime("%Y-%m-%d_%H-%M-%S"))
    rows = []
    for s in a.scenarios.split(","):
        for name, ov in FAMILIES[a.family].items():
            r = {"variant": name, **run_variant(s, ov, a.train, a.test, a.seed)}
            rows.append(r)
            print(f"{s:14s} {name:38s} rmse {r['rmse']:.3f}  nees/2 {r['nees_pos']:.3f}  pred_err "
                  f"{r['pred_err']:.3f}  {r['seconds']:.1f}s", flush=True)
    df = pd.DataFrame(rows)
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / "compare.csv.partial"
    df.to_csv(tmp, index=False)
    tmp.replace(out / "compare.csv")
    fmt = lambda m, s: f"{m:.3f} ± {s:.3f}"  # noqa: E731
    table = pd.DataFrame({
        "scenario": df["scenario"], "variant": df["variant"],
        "rmse [m]": [fmt(m, s) for m, s in zip(df["rmse"], df["rmse_std"])],
        "NEES/2": [fmt(m, s) for m, s in zip(df["nees_pos"], df["nees_pos_std"])],
        "prediction error [m]": [fmt(m, s) for m, s in zip(df["pred_err"], df["pred_err_std"])],
        "s": [f"{v:.1f}" for v in df["seconds"]],
    })
    cols = list(table.columns)
    md = "\n".join(["| " + " | ".join(cols) + " |", "|" + "|".join("---" for _ in cols) + "|",
                     *("| " + " | ".join(str(v) for v in row) + " |" for row in table.itertuples(index=False))])
    (out / "compare.md").write_text(md + "\n", encoding="utf-8")
    print(md)
    print(f"wrote {out / 'compare.csv'} and compare.md")


if __name__ == "__main__":
    main()
