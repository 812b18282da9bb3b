r"""Yu et al. scenario on an unreliable network (the paper's future work).

Tracking error vs per-step link-failure probability and vs the fraction of failed nodes, for
every fusion strategy and for a parametric (LIN) and a learned (increment GP) motion model,
plus gross measurement outliers with and without chi-square gating. Faults act in training and
in test: the GP is learned online through the faulty network.

The parts come from the config groups (:mod:`dslearn.compose`; the grid's models and fusions are
options of the ``model`` and ``consensus`` groups); the faults of the data come from
:mod:`dslearn.sim.faults`, those of the links from :mod:`dslearn.fusion.faults`. All cells of one fault
setting share the same episodes, node-failure schedule, outliers and link-failure draws
(common random numbers), so differences between fusions and models are not sampling noise.

``dslearn-run experiment=yu_faults`` (parameters: ``conf/task/yu_faults.yaml``).
"""

from __future__ import annotations

import copy
import logging
import time

import pandas as pd
import torch
from omegaconf import DictConfig

from dslearn.compose import build_fusion, build_motion_model, build_network, build_observation, build_predict
from dslearn.compose import build_scenario, group_options, resolve_device, resolve_dtype
from dslearn.filters.distributed import initial_belief
from dslearn.diagnostics import Diagnostics
from dslearn.fusion.faults import FaultyFusion
from dslearn.learning.online import OnlineLearner
from dslearn.metrics import tracking_metrics
from dslearn.sim.faults import add_outliers, apply_node_failures, node_failure_schedule
from dslearn.sim.scenario import episode_streams
from dslearn.streams import Streams
from dslearn.studies.yu import check_offline, offline_trajectories

log = logging.getLogger(__name__)


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


def grid_fusions(cfg: DictConfig) -> dict[str, DictConfig]:
    """The config node of every fusion of ``task.fusions``, composed from its own ``consensus`` option.

    Each keeps its own ``omega`` (``hybrid``: 1, ``hybrid_nodes``: S) and type; only the number of
    rounds ``L`` is the grid's, ``consensus.iterations``. The weight rule of the option is not used:
    :class:`~dslearn.fusion.faults.FaultyFusion` recomputes the weights on every step's live graph
    (``task.weights``). A root ``consensus.omega`` other than ``one`` would apply to no fusion: the
    schema (:mod:`dslearn.schemas.yu_faults`) refuses it; the grid lists the omega variants as
    options (``task.fusions=[hybrid,hybrid_nodes]``).
    """
    same = (f"consensus.iterations={int(cfg.consensus.iterations)}", "consensus.weights=uniform")
    return group_options("consensus", list(cfg.task.fusions), same)


def run(cfg: DictConfig) -> pd.DataFrame:
    """Task entry point (see :mod:`dslearn.run`); ``cfg.task`` is checked by :mod:`dslearn.schemas.yu_faults`."""
    t = cfg.task
    dtype, device = resolve_dtype(cfg.dtype), resolve_device(cfg.device)
    seed = int(cfg.seed)
    scenario = build_scenario(cfg)
    network = build_network(cfg)
    s = network.num_nodes
    ctx = scenario.ctx()
    models = group_options("model", list(t.models))
    fusions = grid_fusions(cfg)
    grid = settings(t)
    cells = len(grid) * len(t.models) * len(t.fusions)
    frames, k, t0 = [], 0, time.perf_counter()
    offline = fit_offline_models(models, scenario, network, ctx, t.train_episodes, seed, dtype, device)
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
            faulty[split] = (ep.to(dtype, device), alive)
        for mname in t.models:
            for fname in t.fusions:
                k += 1
                df = _cell(cfg, st, si, scenario, network, ctx, models[mname], fname, fusions[fname], faulty, dtype, device,
                           seed, offline[mname])
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


def fit_offline_models(models: dict, scenario, network, ctx, train_episodes: int, seed: int, dtype, device) -> dict:
    """The offline models of the grid (``model.learns_offline``: the LSTM), each fitted once, before any cell,
    on the true tracks of the training episodes, which every fault setting shares (faults act on the
    measurements and the links only; :func:`dslearn.studies.yu.offline_trajectories`); ``{name: model or
    None}`` (None: a model built per cell). What a model cannot learn from is refused before any work."""
    out, probes = {}, {}
    for name, node in models.items():
        with torch.random.fork_rng(devices=[]):  # a probe: shapes only (meta device), no draw of the run's
            probes[name] = build_motion_model(node, scenario, network, dtype, torch.device("meta"))
        if probes[name].learns_offline:
            check_offline(probes[name])
        out[name] = None
    if any(p.learns_offline for p in probes.values()):
        train = scenario.sample(train_episodes, network, episode_streams(seed, "train", 0, train_episodes))
        for name, probe in probes.items():
            if probe.learns_offline:
                model = build_motion_model(models[name], scenario, network, dtype, device)
                out[name] = model.fit_offline(offline_trajectories(model, train).to(device, dtype), ctx.dt, seed=seed)
    return out


def _cell(cfg, st, si, scenario, network, ctx, mcfg, fname, fcfg, faulty, dtype, device, seed, fitted=None) -> pd.DataFrame:
    t = cfg.task
    # an offline model is the one fitted before the grid (a copy per cell); the others are built fresh
    model = copy.deepcopy(fitted) if fitted is not None else build_motion_model(mcfg, scenario, network, dtype, device)
    obs = build_observation(cfg.observation, network, dtype, device)
    fusion = FaultyFusion(build_fusion(fcfg, network), network.adjacency, st["link_fail"], t.weights,
                          seed=seed * 1_000_003 + 31 * si + 7)
    train, alive_tr = faulty["train"]
    test, alive_te = faulty["test"]
    model.begin_episodes(test.states)
    learner = OnlineLearner(
        network, model, obs, fusion, ctx,
        init=lambda ep: initial_belief(ep, network, ctx.dt, fusion, scenario.area, cfg.filter.prior_pos_std, cfg.filter.prior_vel_std),
        predict_step=build_predict(cfg), learn_gate_std=cfg.filter.get("learn_gate_std"), gate_prob=st["gate_prob"],
    )
    def evaluate(_seen: int):
        fusion.begin(alive_te, episodes=list(range(alive_te.shape[1])), split="test")
        return learner.estimate(test.measurements)

    def before(i: int) -> None:
        fusion.begin(alive_tr[:, i : i + 1], episodes=[i], split="train")

    with Diagnostics() as cell:  # this cell's gating counts (the run's diagnostics get them too)
        if model.learnable:
            learner.run(train.measurements, [len(train)], lambda k: pd.DataFrame(), before=before)
        res = evaluate(len(train))
    return _cell_rows(cfg, st, mcfg, fname, fusion, res, test, alive_te, cell)


def _cell_rows(cfg, st, mcfg, fname, fusion, res, test, alive_te, cell: Diagnostics) -> pd.DataFrame:
    t = cfg.task
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
    tested, rej = cell.gate_tested, cell.gate_rejected
    rows.append(pd.DataFrame({"node": "all", "episode": [0], "metric": "gate_reject_frac",
                              "value": [rej / tested if tested else 0.0]}))
    df = pd.concat(rows, ignore_index=True)
    keys = dict(model=str(mcfg.name), consensus=fname, link_fail=st["link_fail"], node_fail=st["node_fail"],
                outlier_frac=st["outlier_frac"], gating="chi2" if st["gate_prob"] is not None else "none",
                axis=st["axis"], node_fail_mode=t.node_fail_mode, weights=t.weights,
                iterations=int(cfg.consensus.iterations), train_episodes=int(t.train_episodes))
    for i, (key, v) in enumerate(keys.items()):
        df.insert(i, key, v)
    return df
