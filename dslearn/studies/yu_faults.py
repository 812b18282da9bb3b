r"""Yu et al. scenario on an unreliable network (the paper's future work).

Tracking error vs per-step link-failure probability and vs the fraction of failed nodes, for
every fusion strategy and for a parametric (LIN) and a learned (increment GP) motion model,
plus gross measurement outliers with and without chi-square gating. Faults act in training and
in test: the GP is learned online through the faulty network.

Builds the scenario, network, models and fusions with the Yu study's builders
(:mod:`dslearn.studies.yu`); faults come from :mod:`dslearn.fusion.faults`. All cells of one fault
setting share the same episodes, node-failure schedule, outliers and link-failure draws
(common random numbers), so differences between fusions and models are not sampling noise.

``dslearn-run experiment=yu_faults`` (parameters: ``conf/task/yu_faults.yaml``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional

import pandas as pd
import torch
from omegaconf import DictConfig, OmegaConf

from dslearn.config_schema import check_schema
from dslearn.fusion.strategies import FUSIONS, make_fusion
from dslearn.fusion.weights import consensus_weights
from dslearn.errors import ConfigError, check_choice, check_positive
from dslearn.fusion.faults import (
    LIVE_WEIGHTS,
    NODE_FAIL_MODES,
    FaultyFusion,
    add_outliers,
    apply_node_failures,
    node_failure_schedule,
)
from dslearn.config_schema import CONF_DIR
from dslearn.filters.information import GATE_STATS
from dslearn.sim.scenario import episode_streams
from dslearn.streams import Streams
from dslearn.filters.distributed import initial_belief, track, tracking_metrics
from dslearn.studies.yu import (
    DTYPES,
    _resolve_device,
    _to,
    build_motion_model,
    build_network,
    build_observation,
    build_scenario,
)

log = logging.getLogger(__name__)
CONF = CONF_DIR


@dataclass
class FaultTask:
    """Schema of ``cfg.task`` (conf/task/yu_faults.yaml)."""

    entry: str = "dslearn.studies.yu_faults:run"
    name: str = "yu_faults"
    models: List[str] = field(default_factory=lambda: ["lin", "gp_increment"])
    fusions: List[str] = field(default_factory=lambda: ["individual", "ce", "cm", "ci", "hybrid", "centralized"])
    train_episodes: int = 15
    test_episodes: int = 20
    link_fail: List[float] = field(default_factory=lambda: [0.0, 0.1, 0.3, 0.5])
    node_fail: List[float] = field(default_factory=lambda: [0.0, 0.1, 0.2, 0.4])
    joint: List[List[float]] = field(default_factory=lambda: [[0.3, 0.2]])
    node_fail_mode: str = "permanent"
    node_fail_duration: int = 4
    weights: str = "metropolis"
    outlier_frac: float = 0.1
    outlier_std: float = 3.0
    gate_prob: Optional[float] = 0.99
    outlier_settings: bool = True
    divergence_bound: float = 2.0


def validate(cfg: DictConfig) -> DictConfig:
    t = check_schema(cfg.task, FaultTask, "task")
    for m in t.models:
        if not (CONF / "model" / f"{m}.yaml").is_file():
            raise ConfigError(f"task.models contains {m!r}: no conf/model/{m}.yaml")
    for f in t.fusions:
        check_choice("task.fusions[]", f, FUSIONS)
    if t.train_episodes < 0:
        raise ConfigError(f"task.train_episodes={t.train_episodes} must be >= 0")
    if t.test_episodes < 1:
        raise ConfigError(f"task.test_episodes={t.test_episodes} must be >= 1")
    for name, vals in (("task.link_fail", t.link_fail), ("task.node_fail", t.node_fail)):
        for v in vals:
            if not 0.0 <= v <= 1.0:
                raise ConfigError(f"{name} contains {v}: must be a probability/fraction in [0, 1]")
    for pair in t.joint:
        if len(pair) != 2 or not all(0.0 <= v <= 1.0 for v in pair):
            raise ConfigError(f"task.joint contains {list(pair)!r}: must be [link_fail, node_fail] in [0, 1]")
    check_choice("task.node_fail_mode", t.node_fail_mode, NODE_FAIL_MODES)
    check_choice("task.weights", t.weights, LIVE_WEIGHTS)
    if t.node_fail_duration < 1:
        raise ConfigError(f"task.node_fail_duration={t.node_fail_duration} must be >= 1")
    if not 0.0 <= t.outlier_frac <= 1.0:
        raise ConfigError(f"task.outlier_frac={t.outlier_frac} must be in [0, 1]")
    check_positive("task.outlier_std", t.outlier_std)
    if t.gate_prob is not None and not 0.0 < t.gate_prob < 1.0:
        raise ConfigError(f"task.gate_prob={t.gate_prob} must be in (0, 1) or null")
    check_positive("task.divergence_bound", t.divergence_bound)
    return t


def load_model_cfg(name: str) -> DictConfig:
    """``conf/model/<name>.yaml`` with its ``defaults`` (e.g. gp_increment -> gp) merged in."""
    node = OmegaConf.load(CONF / "model" / f"{name}.yaml")
    defaults = node.pop("defaults", [])
    parts = []
    for d in defaults:
        if d == "_self_":
            parts.append(node)
        else:
            parts.append(load_model_cfg(str(d)))
    if not any(d == "_self_" for d in defaults):
        parts.append(node)
    return OmegaConf.merge(*parts) if parts else node


def settings(t) -> list[dict]:
    """The fault settings of the grid: link axis, node axis, joint points, outliers."""
    out, seen = [], set()

    def add(p, f, outl=0.0, gate=None, axis=""):
        key = (p, f, outl, gate)
        if key not in seen:
            seen.add(key)
            out.append({"link_fail": p, "node_fail": f, "outlier_frac": outl, "gate_prob": gate, "axis": axis})

    for p in t.link_fail:
        add(float(p), 0.0, axis="link")
    for f in t.node_fail:
        add(0.0, float(f), axis="node")
    for p, f in t.joint:
        add(float(p), float(f), axis="joint")
    if t.outlier_settings and t.outlier_frac > 0:
        add(0.0, 0.0, float(t.outlier_frac), None, axis="outliers")
        if t.gate_prob is not None:
            add(0.0, 0.0, float(t.outlier_frac), float(t.gate_prob), axis="outliers")
            for p, f in t.joint:
                add(float(p), float(f), float(t.outlier_frac), float(t.gate_prob), axis="joint+outliers")
    return out


def run(cfg: DictConfig) -> pd.DataFrame:
    """Task entry point (see :mod:`dslearn.run`)."""
    t = validate(cfg)
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    dtype, device = DTYPES[str(cfg.dtype)], _resolve_device(str(cfg.device))
    seed = int(cfg.seed)
    scenario = build_scenario(cfg.scenario)
    network = build_network(cfg.network)
    s = network.num_nodes
    ctx = scenario.ctx()
    steps = int(round(scenario.horizon / scenario.dt)) if hasattr(scenario, "horizon") else None
    models = {m: load_model_cfg(m) for m in t.models}
    grid = settings(t)
    cells = len(grid) * len(t.models) * len(t.fusions)
    frames, k, t0 = [], 0, time.perf_counter()
    from tqdm.auto import tqdm

    bar = tqdm(total=cells, desc="yu_faults cells", disable=not bool(cfg.get("progress") or False))
    for si, st in enumerate(grid):
        # common random numbers: the same data and faults for every model x fusion of a setting;
        # one stream per episode, so an episode's data and faults do not depend on the batch size
        test = scenario.sample(t.test_episodes, network, episode_streams(seed, "test", 0, t.test_episodes))
        train = scenario.sample(t.train_episodes, network, episode_streams(seed, "train", 0, t.train_episodes))
        steps = test.states.shape[1] - 1
        faulty = {}
        for split, ep in (("test", test), ("train", train)):
            if len(ep) == 0:
                faulty[split] = (ep, torch.ones(s, 0, steps + 1, dtype=torch.bool))
                continue
            gs = Streams.from_keys([(seed, "faults", si, split, e) for e in range(len(ep))], (len(ep),))
            alive = node_failure_schedule(s, len(ep), steps, st["node_fail"], gs, t.node_fail_mode, t.node_fail_duration)
            ep = apply_node_failures(ep, alive)
            if st["outlier_frac"] > 0:
                ep, _ = add_outliers(ep, st["outlier_frac"], t.outlier_std, gs)
            faulty[split] = (_to(ep, dtype, device), alive)
        for mname in t.models:
            for fname in t.fusions:
                k += 1
                df = _cell(cfg, t, st, si, scenario, network, ctx, models[mname], fname, faulty, dtype, device, seed)
                frames.append(df)
                bar.update(1)
                te = df[(df.metric == "track_err") & (df.node == "alive")]["value"].mean()
                log.info(
                    "cell %d/%d: link_fail=%.2f node_fail=%.2f outliers=%.2f gate=%s %s/%s: track_err(alive)=%.3f (%.0fs)",
                    k, cells, st["link_fail"], st["node_fail"], st["outlier_frac"], st["gate_prob"], mname, fname, te,
                    time.perf_counter() - t0,
                )
    bar.close()
    out = pd.concat(frames, ignore_index=True)
    bad = out[out.metric == "nonfinite"]["value"].sum()
    if bad:
        log.warning("%d non-finite estimates in the grid", int(bad))
    return out


def _cell(cfg, t, st, si, scenario, network, ctx, mcfg, fname, faulty, dtype, device, seed) -> pd.DataFrame:
    s = network.num_nodes
    model = build_motion_model(mcfg, scenario, s, dtype, device)
    obs = build_observation(cfg.observation, s, dtype, device)
    base = make_fusion(fname, consensus_weights(network.adjacency, "uniform"), cfg.consensus.iterations, cfg.consensus.omega)
    fusion = FaultyFusion(base, network.adjacency, st["link_fail"], t.weights, seed=seed * 1_000_003 + 31 * si + 7)
    gate = st["gate_prob"]

    def init(ep):
        return initial_belief(ep, network, ctx.dt, fusion, scenario.area, cfg.filter.prior_pos_std, cfg.filter.prior_vel_std)

    train, alive_tr = faulty["train"]
    test, alive_te = faulty["test"]
    g0 = dict(GATE_STATS)
    if model.learnable:
        for i in range(len(train)):
            ep = train.select(slice(i, i + 1))
            fusion.begin(alive_tr[:, i : i + 1], episodes=[i], split="train")
            track(ep, network, model, obs, fusion, ctx, init(ep), learn=True,
                  learn_gate_std=cfg.filter.get("learn_gate_std"), gate_prob=gate)
    fusion.begin(alive_te, episodes=list(range(alive_te.shape[1])), split="test")
    with torch.no_grad():
        res = track(test, network, model, obs, fusion, ctx, init(test), learn=False, gate_prob=gate)
    m = tracking_metrics(res, test.states)  # (S, B) each
    finite = torch.isfinite(res.mean).all(-1).all(-1)  # (S, B)
    alive_end = alive_te[:, :, -1].to(finite.device)  # (S, B)
    rows = []
    b = len(test)
    for name, v in m.items():
        v = v.detach().cpu().double()
        vz = torch.where(torch.isfinite(v), v, torch.full_like(v, float("nan")))
        a = alive_end.cpu().double()
        alive_mean = (vz * a).nansum(0) / a.sum(0).clamp_min(1)
        alive_max = torch.where(a > 0, vz, torch.full_like(vz, float("-inf"))).max(0).values
        for node, val in (("alive", alive_mean), ("all", vz.mean(0)), ("alive_max", alive_max)):
            rows.append(pd.DataFrame({"node": node, "episode": range(b), "metric": name, "value": val.numpy()}))
    rows.append(pd.DataFrame({"node": "all", "episode": range(b), "metric": "nonfinite",
                              "value": (~finite).sum(0).double().cpu().numpy()}))
    links = fusion.live_links / fusion.nominal_links if fusion.nominal_links else float("nan")
    rows.append(pd.DataFrame({"node": "all", "episode": [0], "metric": "live_link_frac", "value": [links]}))
    tested = GATE_STATS["tested"] - g0["tested"]
    rej = GATE_STATS["rejected"] - g0["rejected"]
    rows.append(pd.DataFrame({"node": "all", "episode": [0], "metric": "gate_reject_frac",
                              "value": [rej / tested if tested else 0.0]}))
    df = pd.concat(rows, ignore_index=True)
    df.insert(0, "model", str(mcfg.name))
    df.insert(1, "consensus", fname)
    df.insert(2, "link_fail", st["link_fail"])
    df.insert(3, "node_fail", st["node_fail"])
    df.insert(4, "outlier_frac", st["outlier_frac"])
    df.insert(5, "gating", "chi2" if st["gate_prob"] is not None else "none")
    df.insert(6, "axis", st["axis"])
    df.insert(7, "node_fail_mode", t.node_fail_mode)
    df.insert(8, "weights", t.weights)
    df.insert(9, "iterations", int(cfg.consensus.iterations))
    df.insert(10, "train_episodes", int(t.train_episodes))
    return df


# ------------------------------------------------------------------------------------------
# report


def report(results: pd.DataFrame, summary: pd.DataFrame, out_dir: Path) -> str:
    """Curves (PNG) and tables (Markdown + CSV) of tracking error vs faults."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dslearn.report import markdown

    out_dir = Path(out_dir)
    r = results[(results.metric == "track_err") & (results.node == "alive")]
    keys = ["model", "consensus", "axis", "link_fail", "node_fail", "outlier_frac", "gating"]
    g = r.groupby(keys, sort=False)["value"].agg(mean="mean", std="std", n="count").reset_index()
    md = ["## Tracking error under network faults (mean ± std over test episodes, nodes alive at the end)"]

    def axis_rows(axis: str) -> pd.DataFrame:
        # the fault-free setting (p = 0, f = 0) is listed once (link axis) and belongs to both curves
        base = g[(g.axis == "link") & (g.link_fail == 0) & (g.node_fail == 0)]
        sub = g[g.axis == axis]
        return sub if axis == "link" else pd.concat([base, sub], ignore_index=True)

    def table(axis: str, col: str) -> pd.DataFrame:
        sub = axis_rows(axis).copy()
        sub["cell"] = sub["mean"].map("{:.3f}".format) + " ± " + sub["std"].map("{:.3f}".format)
        return sub.pivot_table(index=["model", "consensus"], columns=col, values="cell", aggfunc="first", sort=False)

    # the link axis includes p = 0 (no faults); the node axis too
    for axis, col, title in (("link", "link_fail", "vs link-failure probability p"),
                             ("node", "node_fail", "vs fraction of failed nodes")):
        tab = table(axis, col)
        if len(tab):
            tab.to_csv(out_dir / f"yu_faults_{axis}.csv")
            md.append(f"### {title}\n\n" + markdown(tab.reset_index()))
    other = g[g.axis.isin(["joint", "outliers", "joint+outliers"])].copy()
    if len(other):
        other["cell"] = other["mean"].map("{:.3f}".format) + " ± " + other["std"].map("{:.3f}".format)
        other["setting"] = (
            "p=" + other.link_fail.astype(str) + ", f=" + other.node_fail.astype(str)
            + ", outliers=" + other.outlier_frac.astype(str) + ", gate=" + other.gating
        )
        tab = other.pivot_table(index=["model", "consensus"], columns="setting", values="cell", aggfunc="first", sort=False)
        tab.to_csv(out_dir / "yu_faults_joint.csv")
        md.append("### joint faults and outliers\n\n" + markdown(tab.reset_index()))
    nf = results[results.metric == "nonfinite"]["value"].sum()
    mx = results[(results.metric == "track_err") & (results.node == "alive_max")]
    worst = mx.groupby(["model", "consensus", "axis", "link_fail", "node_fail", "outlier_frac", "gating"], sort=False)["value"].max()
    worst = worst.reset_index().rename(columns={"value": "worst alive-node track_err"})
    worst.to_csv(out_dir / "yu_faults_worst.csv", index=False)
    hyb = worst[(worst.consensus == "hybrid") & (worst.outlier_frac == 0)]
    md.append(
        f"non-finite estimates in the whole grid: {int(nf)}. Worst alive-node tracking error of hybrid consensus "
        f"over every test episode and fault setting without outliers: {hyb['worst alive-node track_err'].max():.3f} m "
        f"(per-setting maxima: yu_faults_worst.csv)."
    )
    text = "\n\n".join(md)
    (out_dir / "yu_faults.md").write_text(text + "\n")
    # figures: one panel per model, one curve per fusion
    models = list(dict.fromkeys(g.model))
    for axis, col, xl in (("link", "link_fail", "link-failure probability p"), ("node", "node_fail", "fraction of failed nodes")):
        sub = axis_rows(axis)
        if (sub.axis == axis).sum() == 0:
            continue
        fig, axs = plt.subplots(1, len(models), figsize=(4.6 * len(models), 3.6), squeeze=False, sharey=True)
        for ax, m in zip(axs[0], models):
            for fu, c in sub[sub.model == m].groupby("consensus", sort=False):
                c = c.sort_values(col)
                ax.errorbar(c[col], c["mean"], yerr=c["std"], marker="o", capsize=3, label=fu)
            ax.set_title(m)
            ax.set_xlabel(xl)
            ax.grid(alpha=0.3)
        axs[0][0].set_ylabel("tracking error [m] (alive nodes)")
        axs[0][-1].legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out_dir / f"yu_faults_{axis}.png", dpi=120)
        plt.close(fig)
    return text
