"""The method presets of Yu et al.'s family (``conf/method/<filter>_<model>_<fusion>.yaml``): the distributed
information filter with an EKF or UKF prediction step x five motion models x three fusions, each a plain
YAML file that selects the parts of a matrix cell (``dslearn-run task=matrix method=ekf_gp_hybrid``), the
learner among them (the model's natural one: online for the GP, offline for the LSTMs, none for LIN and SFM).

    python benchmarks/method_presets.py           # (re)write the files
    python benchmarks/method_presets.py --check   # exit 1 if a file is missing or differs from what it would write

Other families' presets (``dgpt_*``, ``fg_ekf``, ``rbpf_em``) are written by hand beside these; the
position-sensor presets of the other papers' engines (``rbpf_em_lin``) are written here too.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "conf" / "method"

#: preset word -> (conf/filter option, what it is)
FILTERS = {"ekf": ("default", "EKF prediction step (linearised at the mean)"),
           "ukf": ("ukf", "UKF prediction step (sigma points through the motion model)")}
#: preset word -> (conf/model option, what it is)
MODELS = {"lin": ("lin", "constant velocity (LIN)"),
          "sfm": ("sfm", "the social force model with the simulation's parameters"),
          "gp": ("gp_increment", "the increment GP, learned online while tracking (Algorithm 1)"),
          "lstm": ("lstm", "the LSTM, trained offline on the training episodes' tracks"),
          "social_lstm": ("social_lstm", "the social LSTM, trained offline on the training episodes' tracks")}
#: model preset word -> its conf/learner option (the distributed filter's natural learner for that model)
LEARNERS = {"lin": "none", "sfm": "none", "gp": "online", "lstm": "offline", "social_lstm": "offline"}
#: model preset word -> its conf/observation option: every learned model and LIN take the scenario's own sensor
#: model (observation=sensor: the linear position sensor on Yu's and Liu's scenarios, the squared range on Jiang's,
#: the terrain altitude on Braga's); the social force model, the simulator's own, takes the walkers' position sensor
OBSERVATIONS = {"lin": "sensor", "sfm": "linear", "gp": "sensor", "lstm": "sensor", "social_lstm": "sensor"}
#: model preset word -> the model's settings in every preset of that model (the matrix's recipe, not the paper's:
#: the LSTMs train with early stopping on held-out training episodes, one fit instead of the fixed schedule's two,
#: and in float32 inside the float64 filter; measured in experiments/matrix/README.md, "Where the time goes")
MODEL_SETTINGS = {m: ("model:\n  schedule: early_stopping\n  patience: 5\n  weights_dtype: float32\n")
                  for m in ("lstm", "social_lstm")}
#: preset word -> (conf/consensus option, what it is)
FUSIONS = {"individual": ("individual", "no fusion (each node alone)"),
           "hybrid": ("hybrid", "hybrid consensus (L = 4 rounds)"),
           "centralized": ("centralized", "a fusion centre")}


def presets() -> dict[str, str]:
    """File name -> text of every preset."""
    out = {}
    for f, (f_opt, f_what) in FILTERS.items():
        for m, (m_opt, m_what) in MODELS.items():
            for c, (c_opt, c_what) in FUSIONS.items():
                name = f"{f}_{m}_{c}"
                out[f"{name}.yaml"] = (
                    "# @package _global_\n"
                    f"# Yu et al.'s distributed filter: {f_what}, {m_what}, {c_what}.\n"
                    f"# Written by benchmarks/method_presets.py (dslearn-run task=matrix method={name}).\n"
                    "defaults:\n"
                    f"  - override /filter: {f_opt}\n"
                    f"  - override /model: {m_opt}\n"
                    f"  - override /observation: {OBSERVATIONS[m]}\n"
                    f"  - override /consensus: {c_opt}\n"
                    f"  - override /learner: {LEARNERS[m]}\n"
                    + MODEL_SETTINGS.get(m, "")
                )
    # the LIN hybrid filter with its numbers learned by backpropagation (learner=backprop: model=lin only)
    out["ekf_lin_hybrid_backprop.yaml"] = out["ekf_lin_hybrid.yaml"].replace(
        "hybrid consensus (L = 4 rounds).", "hybrid consensus (L = 4 rounds), Q, R, consensus weights and omega "
        "learned by backpropagation (learner=backprop).").replace(
        "method=ekf_lin_hybrid)", "method=ekf_lin_hybrid_backprop)").replace("learner: none", "learner: backprop").replace(
        "observation: sensor", "observation: linear")  # learner=backprop learns the linear position sensor's R
    # the GP-Bayes filters' prediction steps with the increment GP learned online (dslearn/filters/adf.py,
    # ukf.py with the expected variance, particle.py)
    for word, opt, what in (("adf", "adf", "GP-ADF prediction step (exact moments of the GP prediction at the belief)"),
                            ("ukf_mm", "ukf_mm", "GP-UKF prediction step with the GP variance averaged over the "
                                                 "sigma points"),
                            ("pf", "pf", "GP-PF prediction step (500 particles through the GP, moment-matched)")):
        out[f"{word}_gp_hybrid.yaml"] = out["ekf_gp_hybrid.yaml"].replace(
            "EKF prediction step (linearised at the mean)", what).replace(
            "method=ekf_gp_hybrid)", f"method={word}_gp_hybrid)").replace("override /filter: default",
                                                                          f"override /filter: {opt}")
    # the motion models' own parameters learned by backpropagation (learner=backprop, learn: [model, ...])
    for m, learn, extra, what in (
            ("sfm", "[model, q, r, weights, omega]", "", "its tau, alpha, beta, Q, R, consensus weights and omega"),
            ("gp", "[model, r, weights, omega]", "", "its hyperparameters (on the data gathered online), R, "
                                                     "consensus weights and omega"),
            ("lstm", "[model, q, r, weights, omega]", "  model_lr: 1.0e-4\n", "its weights (after the offline fit), "
                                                                             "Q, R, consensus weights and omega")):
        base = out[f"ekf_{m}_hybrid.yaml"]
        out[f"ekf_{m}_hybrid_backprop.yaml"] = base.replace(
            "hybrid consensus (L = 4 rounds).", f"hybrid consensus (L = 4 rounds), {what} learned by "
            "backpropagation (learner=backprop).").replace(
            f"method=ekf_{m}_hybrid)", f"method=ekf_{m}_hybrid_backprop)").replace(
            f"learner: {LEARNERS[m]}", "learner: backprop").replace(
            "observation: sensor", "observation: linear") + f"learner:\n  learn: {learn}\n{extra}"
    # the noises calibrated to the scenario (learner=calibrate: a scale of Q and of R by maximum likelihood of the
    # nodes' training innovations, after the model's own learner: the GP online, the LSTM offline)
    for m, what in (("lin", "LIN's Q"), ("sfm", "the social force's Q"), ("gp", "the GP's predictive variance"),
                    ("lstm", "the LSTM's Q (its held-out residuals' covariance)")):
        out[f"ekf_{m}_hybrid_calibrated.yaml"] = out[f"ekf_{m}_hybrid.yaml"].replace(
            "hybrid consensus (L = 4 rounds).", f"hybrid consensus (L = 4 rounds), a scale of {what} and of R fitted to "
            "the training measurements (learner=calibrate).").replace(
            f"method=ekf_{m}_hybrid)", f"method=ekf_{m}_hybrid_calibrated)").replace(
            f"learner: {LEARNERS[m]}", "learner: calibrate").replace("observation: sensor", "observation: linear")
    # the social force fitted to the scenario (model=sfm_fit: shared tau, alpha, beta by grid search and Adam on the
    # training episodes' tracks, learner=offline): the social force's row on the scenarios that do not simulate it
    out["ekf_sfm_fit_hybrid.yaml"] = out["ekf_sfm_hybrid.yaml"].replace(
        "the social force model with the simulation's parameters", "the social force model fitted offline to the "
        "training episodes' tracks").replace("method=ekf_sfm_hybrid)", "method=ekf_sfm_fit_hybrid)").replace(
        "override /model: sfm", "override /model: sfm_fit").replace("learner: none", "learner: offline")
    # the other papers' engines taken apart, on the position-sensor scenarios: Braga et al.'s RBPF + online EM +
    # consensus on the statistics over a constant-velocity state (dslearn/methods/rbpf_modes.py)
    out["rbpf_em_lin.yaml"] = (
        "# @package _global_\n"
        "# Braga et al.'s RBPF over jump-Markov sensor noise modes (a Kalman filter of the constant-velocity state per\n"
        "# particle), online EM of the modes, 10 rounds of consensus on the EM statistics; the scenario's own sensor\n"
        "# model: position sensors (every node's Kalman filters) or a nonlinear sensor such as Jiang's squared ranges\n"
        "# (a fusion centre's extended Kalman filter per particle).\n"
        "# Written by benchmarks/method_presets.py (dslearn-run task=matrix method=rbpf_em_lin).\n"
        "defaults:\n"
        "  - override /filter: rbpf_em_lin\n"
        "  - override /observation: sensor\n"
        "  - override /consensus: statistics\n"
        "  - override /learner: online_em_sensor\n"
    )
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="compare instead of writing")
    a = p.parse_args(argv)
    want = presets()
    if a.check:
        bad = [n for n, t in want.items() if not (OUT / n).is_file() or (OUT / n).read_text() != t]
        for n in bad:
            print(f"conf/method/{n}: missing or not what benchmarks/method_presets.py writes", file=sys.stderr)
        return 1 if bad else 0
    OUT.mkdir(parents=True, exist_ok=True)
    for n, t in want.items():
        (OUT / n).write_text(t)
    print(f"wrote {len(want)} presets into conf/method/")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
