r"""Study ``jiang_fg``: factor-graph identification + EKF-FG tracking (Jiang et al., ISITA 2022).

One run computes all four figures' grids, vectorised over configurations and Monte Carlo runs:

* ``fig2``: RMSE of the FG identification after ``t = 0..T`` iterations (``fg_identification``)
  and of the EKF-FG tracker run with ``t`` iterations per timing (``ekf_fg``); centralised
  baselines and CRLB as reference rows (``iteration = -1``).
* ``fig3``: estimates vs truth over time (first ``figures.fig3_episodes`` episodes), ``metric = estimate``.
* ``fig4``: RMSE per timing index.
* ``fig5``: RMSE averaged over timings vs ``sigma_y``.
* ``diag``: near-zero slopes (skipped sensors), precision floors, iterations to converge,
  the EKF-FG observation variance and the fraction of gated FG outputs.

``variant`` is ``default`` for the main grid (the settings of ``conf/task/jiang_fg.yaml``) or
the name of an ablation (``task.ablations``), run on the same data; ``paper`` is the paper's
EKF-FG (``sigma_e^2`` = CRLB at the prediction). Monte Carlo run ``r`` draws its truth and
noise from its own stream seeded by ``(seed, r)`` (:func:`~dslearn.sim.squared_range.run_noise`),
so its rows do not depend on ``task.mc_runs``.

``rmse`` rows hold one episode's root-mean-square error per parameter (mean over the M
parameters and, where ``timing = -1``, over all timings). The report pools episodes as
``sqrt(mean(rmse^2))`` (the Monte Carlo RMSE); ``summary.csv``'s ``mean`` is the plain mean.
The CRLB rows hold ``sqrt(tr F^{-1} / M)`` at the true state (Eq. 27), the same units.
"""

from __future__ import annotations

import math
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig, OmegaConf

from dslearn.errors import ConfigError, check_choice, check_positive
from dslearn.learning.factor_graph.crlb import CRLB_FORMS
from dslearn.learning.factor_graph.identification import GRAPHS, SCHEDULES
from dslearn.sim.squared_range import SquaredRange, polynomial_trajectory, run_noise
from dslearn.learning.factor_graph.engine import TrackerSettings, simulate
from dslearn.filters.ekf_fg import OBS_VAR_MODES

MODELS = ("fg_identification", "ekf_fg", "centralized_gn", "centralized_ekf")
CONSENSUS = {"fg_identification": "gaussian_bp", "ekf_fg": "gaussian_bp", "centralized_gn": "centralized",
             "centralized_ekf": "centralized", "crlb": "-", "truth": "-"}
NODE = "fusion_center"
MAIN = "default"   # variant label of the main grid (the settings of conf/task/jiang_fg.yaml)


# ----------------------------------------------------------------------------- config
def _int(field: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ConfigError(f"{field}={value!r} must be an integer >= {minimum}")
    return int(value)


def _floats(field: str, value, length: int | None = None) -> list[float]:
    try:
        out = [float(v) for v in value]
    except (TypeError, ValueError):
        raise ConfigError(f"{field}={value!r} must be a list of numbers") from None
    if length is not None and len(out) != length:
        raise ConfigError(f"{field}={value!r} must have {length} entries")
    if not all(math.isfinite(v) for v in out):
        raise ConfigError(f"{field}={value!r} must be finite")
    return out


def validate(task: DictConfig) -> dict:
    """Check ``cfg.task`` and return plain Python parameters. Raises :class:`ConfigError`."""
    t = OmegaConf.to_container(task, resolve=True)
    p: dict = {}
    p["mc_runs"] = _int("task.mc_runs", t.get("mc_runs"), 1)
    sc = t.get("scenario") or {}
    sensors = sc.get("sensors")
    if not isinstance(sensors, list) or len(sensors) < 1:
        raise ConfigError(f"task.scenario.sensors={sensors!r} must be a non-empty list of positions")
    p["sensors"] = [_floats("task.scenario.sensors[i]", s) for s in sensors]
    M = len(p["sensors"][0])
    if M < 1 or any(len(s) != M for s in p["sensors"]):
        raise ConfigError(f"task.scenario.sensors={sensors!r}: every sensor needs the same number of coordinates")
    coeffs = sc.get("coefficients")
    if not isinstance(coeffs, list) or len(coeffs) != M:
        raise ConfigError(f"task.scenario.coefficients={coeffs!r} needs {M} rows (one per parameter)")
    p["coefficients"] = [_floats("task.scenario.coefficients[m]", c, 3) for c in coeffs]
    check_positive("task.scenario.drive_var", sc.get("drive_var"), strict=False)
    p["drive_var"] = float(sc["drive_var"])
    p["num_timings"] = _int("task.scenario.num_timings", sc.get("num_timings"), 1)
    p["initial_state"] = _floats("task.scenario.initial_state", sc.get("initial_state"), M)
    p["num_samples"] = _int("task.num_samples", t.get("num_samples"), 1)
    check_positive("task.sigma_y", t.get("sigma_y"))
    p["sigma_y"] = float(t["sigma_y"])
    p["max_iter"] = _int("task.max_iter", t.get("max_iter"), 1)
    fg = t.get("fg") or {}
    p["init_guess"] = _floats("task.fg.init_guess", fg.get("init_guess"), M)
    check_choice("task.fg.init_guess_mode", fg.get("init_guess_mode"), ["fixed", "prediction"])
    check_positive("task.fg.init_var", fg.get("init_var"))
    if fg.get("prior_var") is not None:
        check_positive("task.fg.prior_var", fg.get("prior_var"))
    check_choice("task.fg.relinearize", fg.get("relinearize"), [True, False])
    check_choice("task.fg.measurement_var", fg.get("measurement_var"), ["sample", "known"])
    if fg.get("measurement_var") == "sample" and p["num_samples"] < 2:
        raise ConfigError(f"task.num_samples={p['num_samples']} must be >= 2 with task.fg.measurement_var=sample")
    check_choice("task.fg.crlb_form", fg.get("crlb_form"), CRLB_FORMS)
    check_positive("task.fg.lambda_tol", fg.get("lambda_tol"), strict=False)
    check_positive("task.fg.converge_tol", fg.get("converge_tol"))
    tr = t.get("tracker") or {}
    for key in ("initial_state_var", "initial_gradient_var"):
        check_positive(f"task.tracker.{key}", tr.get(key))
    for key in ("process_var", "gradient_var"):
        check_positive(f"task.tracker.{key}", tr.get(key), strict=False)
    fg = {"schedule": "flooding", "damping": 0.0, "graph": "scalar", "taylor_point": "prediction", **fg}
    tr = {"obs_var": "crlb", "gate": None, **tr}
    _check_variant("task.fg", fg)
    _check_variant("task.tracker", tr)
    p["baseline_iters"] = _int("task.baseline_iters", t.get("baseline_iters"), 1)
    figs = t.get("figures") or {}
    its = figs.get("fig2_iterations")
    if not isinstance(its, list) or not its:
        raise ConfigError(f"task.figures.fig2_iterations={its!r} must be a non-empty list of integers >= 1")
    p["fig2_iterations"] = sorted({_int("task.figures.fig2_iterations[i]", i, 1) for i in its})
    p["fig3_episodes"] = _int("task.figures.fig3_episodes", figs.get("fig3_episodes"), 0)
    sig = figs.get("fig5_sigma_y")
    if not isinstance(sig, list) or not sig:
        raise ConfigError(f"task.figures.fig5_sigma_y={sig!r} must be a non-empty list of positive numbers")
    for s in sig:
        check_positive("task.figures.fig5_sigma_y[i]", s)
    p["fig5_sigma_y"] = [float(s) for s in sig]
    settings = dict(
        num_samples=p["num_samples"], init_guess=tuple(p["init_guess"]), init_guess_mode=fg["init_guess_mode"],
        init_var=float(fg["init_var"]),
        prior_var=float("inf") if fg.get("prior_var") is None else float(fg["prior_var"]),
        relinearize=bool(fg["relinearize"]), measurement_var=fg["measurement_var"], crlb_form=fg["crlb_form"],
        initial_state=tuple(p["initial_state"]), initial_state_var=float(tr["initial_state_var"]),
        initial_gradient_var=float(tr["initial_gradient_var"]), process_var=float(tr["process_var"]),
        gradient_var=float(tr["gradient_var"]), baseline_iters=p["baseline_iters"],
        lambda_tol=float(fg["lambda_tol"]), converge_tol=float(fg["converge_tol"]),
        schedule=fg["schedule"], damping=float(fg["damping"]), graph=fg["graph"], taylor_point=fg["taylor_point"],
        obs_var=tr["obs_var"], gate=None if tr["gate"] is None else float(tr["gate"]),
    )
    p["settings"] = settings
    p["ablations"] = {}
    allowed = (set(TrackerSettings.__dataclass_fields__) - {"num_samples", "initial_state"}) | {"max_iter"}
    for name, over in (t.get("ablations") or {}).items():
        if not isinstance(over, dict) or not set(over) <= allowed:
            raise ConfigError(f"task.ablations.{name}={over!r}: keys must be among {sorted(allowed)}")
        _check_variant(f"task.ablations.{name}", over)
        over = dict(over)
        if "init_guess" in over:
            over["init_guess"] = tuple(_floats(f"task.ablations.{name}.init_guess", over["init_guess"], M))
        if "prior_var" in over:
            over["prior_var"] = float("inf") if over["prior_var"] is None else float(over["prior_var"])
        its_ab = _int(f"task.ablations.{name}.max_iter", over.pop("max_iter", p["max_iter"]), 1)
        p["ablations"][str(name)] = ({**settings, **over}, its_ab)
    return p


def _check_variant(prefix: str, d: dict) -> None:
    """The choice / range fields of the FG and tracker settings (main config or one ablation)."""
    choices = {"init_guess_mode": ["fixed", "prediction"], "relinearize": [True, False],
               "measurement_var": ["sample", "known"], "crlb_form": list(CRLB_FORMS), "schedule": list(SCHEDULES),
               "graph": list(GRAPHS), "taylor_point": ["prediction", "guess"], "obs_var": list(OBS_VAR_MODES)}
    for key, allowed in choices.items():
        if key in d:
            check_choice(f"{prefix}.{key}", d[key], allowed)
    if "damping" in d:
        try:
            ok = 0.0 <= float(d["damping"]) < 1.0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ConfigError(f"{prefix}.damping={d['damping']!r} must be a number in [0, 1)")
    if d.get("gate") is not None:
        check_positive(f"{prefix}.gate", d["gate"])
    for key in ("init_var", "prior_var", "process_var", "gradient_var", "initial_state_var", "initial_gradient_var",
                "lambda_tol", "converge_tol"):
        if d.get(key) is not None:
            check_positive(f"{prefix}.{key}", d[key], strict=key not in ("process_var", "gradient_var", "lambda_tol"))


# ----------------------------------------------------------------------------- rows
def _rows(values: np.ndarray, metric: str, **keys) -> pd.DataFrame:
    """Tidy rows from ``values (B,)`` (episode-indexed) or ``(B, K)`` (episode x timing)."""
    values = np.asarray(values, dtype=float)
    B = values.shape[0]
    if values.ndim == 1:
        df = pd.DataFrame({"episode": np.arange(B), "value": values})
    else:
        K = values.shape[1]
        df = pd.DataFrame({"episode": np.repeat(np.arange(B), K), "timing": np.tile(np.arange(1, K + 1), B),
                           "value": values.reshape(-1)})
    df["metric"] = metric
    for k, v in keys.items():
        df[k] = v
    return df


def _rmse(sq: torch.Tensor) -> np.ndarray:
    return sq.sqrt().cpu().numpy()


def run(cfg: DictConfig) -> pd.DataFrame:
    """Run every figure's grid of the study; returns the tidy results table."""
    p = validate(cfg.task)
    device = torch.device(str(cfg.get("device", "cpu")))
    check_choice("dtype", str(cfg.get("dtype", "float64")), ["float64", "float32"])
    dtype = getattr(torch, str(cfg.get("dtype", "float64")))
    seed = cfg.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"seed={seed!r} must be an integer >= 0")
    t0 = time.perf_counter()

    B, K, L = p["mc_runs"], p["num_timings"], p["num_samples"]
    sensors = torch.tensor(p["sensors"], dtype=dtype, device=device)
    h = SquaredRange(sensors)
    N, M = sensors.shape
    # every Monte Carlo run r draws from its own stream seeded by (seed, r): its numbers do not
    # depend on mc_runs or on the other runs; all configurations share them (common random numbers)
    drive, noise = run_noise(int(seed), range(B), K, M, N, L, dtype=dtype, device=device)
    truth = polynomial_trajectory(torch.tensor(p["coefficients"], dtype=dtype, device=device), K, p["drive_var"],
                                  noise=drive)

    # configuration grid: (sigma_y, iterations) -- fig2 varies t, fig5 varies sigma_y
    T, s0 = p["max_iter"], p["sigma_y"]
    grid = sorted({(s0, t) for t in p["fig2_iterations"]} | {(s, T) for s in p["fig5_sigma_y"]} | {(s0, T)})
    index = {g: i for i, g in enumerate(grid)}
    sig = torch.tensor([g[0] for g in grid], dtype=dtype, device=device)
    its = torch.tensor([g[1] for g in grid], device=device)
    out = simulate(h, truth, noise, sig, its, TrackerSettings(**p["settings"]))

    frames = []
    base = dict(node=NODE, variant=MAIN)
    err = {m: (out.estimates[m] - truth).square().mean(-1) for m in MODELS}  # (C, B, K)
    crlb = out.crlb_truth                                                     # (C, B, K)
    ref = index[(s0, T)]
    # Fig. 2: identification RMSE vs iteration (within the T-iteration run), tracker vs its iteration count
    for t in range(out.fg_iter_sqerr.shape[0]):
        frames.append(_rows(_rmse(out.fg_iter_sqerr[t, ref].mean(-1)), "rmse", figure="fig2",
                            model="fg_identification", consensus="gaussian_bp", iteration=t, timing=-1,
                            sigma_y=s0, **base))
    for t in p["fig2_iterations"]:
        frames.append(_rows(_rmse(err["ekf_fg"][index[(s0, t)]].mean(-1)), "rmse", figure="fig2", model="ekf_fg",
                            consensus="gaussian_bp", iteration=t, timing=-1, sigma_y=s0, **base))
    for m in ("centralized_gn", "centralized_ekf"):
        frames.append(_rows(_rmse(err[m][ref].mean(-1)), "rmse", figure="fig2", model=m, consensus="centralized",
                            iteration=-1, timing=-1, sigma_y=s0, **base))
    frames.append(_rows(_rmse(crlb[ref].mean(-1)), "rmse", figure="fig2", model="crlb", consensus="-",
                        iteration=-1, timing=-1, sigma_y=s0, **base))
    # Fig. 3: trajectories of the first episodes
    E = min(p["fig3_episodes"], B)
    if E:
        names = [f"x{m + 1}" for m in range(truth.shape[-1])]
        series = {"truth": truth[:E]} | {m: out.estimates[m][ref, :E] for m in ("fg_identification", "ekf_fg",
                                                                                "centralized_ekf")}
        for model, val in series.items():
            for m, pname in enumerate(names):
                frames.append(_rows(val[..., m].cpu().numpy(), "estimate", figure="fig3", model=model,
                                    consensus=CONSENSUS[model], iteration=T if model != "truth" else -1,
                                    sigma_y=s0, param=pname, **base))
    # Fig. 4: RMSE per timing; Fig. 5: RMSE vs sigma_y
    for m in MODELS:
        frames.append(_rows(_rmse(err[m][ref]), "rmse", figure="fig4", model=m, consensus=CONSENSUS[m],
                            iteration=T if m in ("fg_identification", "ekf_fg") else -1, sigma_y=s0, **base))
    frames.append(_rows(_rmse(crlb[ref]), "rmse", figure="fig4", model="crlb", consensus="-", iteration=-1,
                        sigma_y=s0, **base))
    for s in p["fig5_sigma_y"]:
        c = index[(s, T)]
        for m in MODELS:
            frames.append(_rows(_rmse(err[m][c].mean(-1)), "rmse", figure="fig5", model=m, consensus=CONSENSUS[m],
                                iteration=T if m in ("fg_identification", "ekf_fg") else -1, timing=-1,
                                sigma_y=s, **base))
        frames.append(_rows(_rmse(crlb[c].mean(-1)), "rmse", figure="fig5", model="crlb", consensus="-",
                            iteration=-1, timing=-1, sigma_y=s, **base))
    # diagnostics per configuration
    for (s, t), c in index.items():
        diag = {"near_zero_lambda": out.near_zero_lambda[c].double(), "precision_floor": out.floored[c].double(),
                "iters_to_converge": out.iters_to_converge[c].double().mean(-1),
                "unconverged_fraction": (out.iters_to_converge[c] > T).double().mean(-1),
                "obs_var_mean": out.obs_var[c].mean(-1),
                "gated_fraction": out.gated[c].double() / (K * M)}
        for metric, v in diag.items():
            frames.append(_rows(v.cpu().numpy(), metric, figure="diag", model="fg_identification",
                                consensus="gaussian_bp", iteration=t, timing=-1, sigma_y=s, **base))
    n_zero = int(out.near_zero_lambda.sum())
    n_floor = int(out.floored.sum())
    if n_zero or n_floor:
        warnings.warn(f"jiang_fg: {n_zero} near-zero Taylor slopes (sensor skipped for that parameter) and "
                      f"{n_floor} precision floors; see metric near_zero_lambda / precision_floor", stacklevel=2)
    # ablations: same data, other FG settings, at (sigma_y, max_iter)
    for name, (over, t_ab) in p["ablations"].items():
        o = simulate(h, truth, noise, sig[ref:ref + 1], torch.tensor([t_ab], device=device), TrackerSettings(**over))
        ab = dict(node=NODE, variant=name, figure="fig2", consensus="gaussian_bp", timing=-1, sigma_y=s0)
        for t in range(o.fg_iter_sqerr.shape[0]):
            frames.append(_rows(_rmse(o.fg_iter_sqerr[t, 0].mean(-1)), "rmse", model="fg_identification",
                                iteration=t, **ab))
        e = (o.estimates["ekf_fg"][0] - truth).square().mean(-1)
        frames.append(_rows(_rmse(e.mean(-1)), "rmse", model="ekf_fg", iteration=t_ab, **ab))
    frames.append(_rows(np.array([time.perf_counter() - t0]), "runtime_s", figure="diag", model="all",
                        consensus="-", iteration=-1, timing=-1, sigma_y=float("nan"), **base))
    df = pd.concat(frames, ignore_index=True)
    df["param"] = df["param"].fillna("all") if "param" in df else "all"
    df["timing"] = df["timing"].astype(int)
    cols = ["figure", "variant", "model", "consensus", "node", "iteration", "timing", "sigma_y", "param",
            "metric", "episode", "value"]
    return df[cols + [c for c in df.columns if c not in cols]]


# ----------------------------------------------------------------------------- report
def _pooled(df: pd.DataFrame, keys: list[str]) -> pd.DataFrame:
    """Monte Carlo RMSE ``sqrt(mean over episodes of rmse^2)`` per key combination."""
    return df.assign(sq=df["value"].astype(float) ** 2).groupby(keys, dropna=False)["sq"].mean().pow(0.5).rename("rmse")


def _fmt(x: float) -> str:
    return "nan" if not np.isfinite(x) else (f"{x:.3g}" if abs(x) < 1e4 else f"{x:.2e}")


def _md(table: pd.DataFrame, index_name: str) -> str:
    cols = [str(c) for c in table.columns]
    lines = ["| " + index_name + " | " + " | ".join(cols) + " |", "|" + "---|" * (len(cols) + 1)]
    for idx, row in table.iterrows():
        lines.append(f"| {idx} | " + " | ".join(_fmt(float(v)) for v in row.values) + " |")
    return "\n".join(lines)


def report(results: pd.DataFrame, summary: pd.DataFrame, out_dir: Path) -> str:
    """Paper-shaped tables (``.md``/``.csv``) and figures (``.png``) for Figs. 2-5 from ``results``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    r = results[results["task"] == "jiang_fg"] if "task" in results else results
    rm = r[r["metric"] == "rmse"]
    md = ["## jiang_fg: factor-graph identification and EKF-FG tracking (Jiang et al., ISITA 2022)", "",
          "RMSE per parameter, pooled over Monte Carlo runs as sqrt(mean square); CRLB = sqrt(tr F^-1 / M) "
          "at the true state (Eq. 27).", ""]

    # Fig. 2
    f2 = rm[rm["figure"] == "fig2"]
    f2 = f2.assign(series=f2["model"] + np.where(f2["variant"] == MAIN, "", "[" + f2["variant"] + "]"))
    t_main = int(f2.loc[f2["variant"] == MAIN, "iteration"].max())
    tab2 = _pooled(f2[(f2["iteration"] >= 0) & (f2["iteration"] <= t_main)], ["iteration", "series"]).unstack("series")
    refs = _pooled(f2[f2["iteration"] < 0], ["series"])
    tab2.to_csv(out_dir / "jiang_fg_fig2.csv")
    fig, ax = plt.subplots(figsize=(9, 4.5))
    colors = plt.get_cmap("tab20").colors
    for i, col in enumerate(tab2.columns):
        y = tab2[col].dropna()
        tracker = str(col).startswith("ekf_fg")
        ax.semilogy(y.index, y.values, ls=("--" if tracker else "-") if len(y) > 1 else "none",
                    marker="s" if tracker else "o", ms=4, color=colors[i % len(colors)], label=col)
    for name, v in refs.items():
        ax.axhline(v, ls=":" if name == "crlb" else "--", lw=1, color="k" if name == "crlb" else "gray", label=name)
    ax.set_xlabel("FG iterations"); ax.set_ylabel("RMSE"); ax.set_title("Fig. 2: convergence")
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5)); fig.tight_layout()
    fig.savefig(out_dir / "jiang_fg_fig2.png", dpi=120); plt.close(fig)
    md += ["### Fig. 2: RMSE vs FG iterations (t = 0 is the initial guess)", "", _md(tab2, "iteration"), "",
           "Reference (all timings): " + ", ".join(f"{k} = {_fmt(v)}" for k, v in refs.items()), ""]
    # variants (ablations) at their own final iteration count
    fin = f2[f2["model"].isin(["fg_identification", "ekf_fg"])]
    last = fin.groupby(["variant", "model"])["iteration"].transform("max")
    tabv = _pooled(fin[fin["iteration"] == last], ["variant", "model"]).unstack("model")
    tabv["iterations"] = fin[fin["model"] == "ekf_fg"].groupby("variant")["iteration"].max()
    tabv.to_csv(out_dir / "jiang_fg_variants.csv")
    md += ["### Variants: RMSE at the final iteration (same data)", "", _md(tabv, "variant"), ""]

    # Fig. 3
    f3 = r[(r["figure"] == "fig3") & (r["metric"] == "estimate") & (r["episode"] == r["episode"].min())]
    if len(f3):
        params = sorted(f3["param"].unique())
        fig, axes = plt.subplots(1, len(params), figsize=(5 * len(params), 4))
        axes = np.atleast_1d(axes)
        for ax, prm in zip(axes, params):
            for model, g in f3[f3["param"] == prm].groupby("model"):
                g = g.sort_values("timing")
                ax.plot(g["timing"], g["value"], "k-" if model == "truth" else "--", marker=None if model == "truth"
                        else ".", label=model, lw=1)
            ax.set_xlabel("timing k"); ax.set_ylabel(prm); ax.legend(fontsize=7)
        fig.suptitle("Fig. 3: estimates vs truth (episode 0)"); fig.tight_layout()
        fig.savefig(out_dir / "jiang_fg_fig3.png", dpi=120); plt.close(fig)
        wide = f3.pivot_table(index=["param", "timing"], columns="model", values="value")
        wide.to_csv(out_dir / "jiang_fg_fig3.csv")
        dev = r[(r["figure"] == "fig3") & (r["metric"] == "estimate")].pivot_table(
            index=["episode", "param", "timing"], columns="model", values="value")
        gaps = {m: float((dev[m] - dev["truth"]).abs().max()) for m in dev.columns if m != "truth"}
        md += ["### Fig. 3: tracking vs truth", "", "Max |estimate - truth| over the stored episodes: "
               + ", ".join(f"{k} = {_fmt(v)}" for k, v in gaps.items()), ""]

    # Fig. 4
    f4 = rm[(rm["figure"] == "fig4") & (rm["variant"] == MAIN)]
    tab4 = _pooled(f4, ["timing", "model"]).unstack("model")
    tab4.to_csv(out_dir / "jiang_fg_fig4.csv")
    fig, ax = plt.subplots(figsize=(6, 4))
    for col in tab4.columns:
        ax.semilogy(tab4.index, tab4[col], label=col, ls=":" if col == "crlb" else "-")
    ax.set_xlabel("timing index k"); ax.set_ylabel("RMSE"); ax.set_title("Fig. 4: RMSE vs timing")
    ax.legend(fontsize=7); fig.tight_layout(); fig.savefig(out_dir / "jiang_fg_fig4.png", dpi=120); plt.close(fig)
    sel = [k for k in (1, 2, 3, 5, 10, 20, 30, 40, 50) if k in tab4.index]
    md += ["### Fig. 4: RMSE vs timing index (selected k; full table in jiang_fg_fig4.csv)", "",
           _md(tab4.loc[sel], "k"), "", "Average over k: " + ", ".join(
               f"{c} = {_fmt(v)}" for c, v in _pooled(f4.assign(timing=0), ["model"]).items()), ""]

    # Fig. 5
    f5 = rm[(rm["figure"] == "fig5") & (rm["variant"] == MAIN)]
    tab5 = _pooled(f5, ["sigma_y", "model"]).unstack("model")
    tab5.to_csv(out_dir / "jiang_fg_fig5.csv")
    fig, ax = plt.subplots(figsize=(6, 4))
    for col in tab5.columns:
        ax.loglog(tab5.index, tab5[col], marker="o", label=col, ls=":" if col == "crlb" else "-")
    ax.set_xlabel("sigma_y"); ax.set_ylabel("average RMSE"); ax.set_title("Fig. 5: RMSE vs sigma_y")
    ax.legend(fontsize=7); fig.tight_layout(); fig.savefig(out_dir / "jiang_fg_fig5.png", dpi=120); plt.close(fig)
    md += ["### Fig. 5: average RMSE vs sigma_y", "", _md(tab5, "sigma_y"), ""]

    # diagnostics
    dg = r[r["figure"] == "diag"]
    dg = dg[dg["metric"] != "runtime_s"]
    if len(dg):
        tabd = dg.groupby(["sigma_y", "iteration", "metric"])["value"].mean().unstack("metric")
        tabd.to_csv(out_dir / "jiang_fg_diagnostics.csv")
        tabd.index = [f"sigma_y={s:g}, T={t}" for s, t in tabd.index]
        md += ["### Diagnostics (mean per episode)", "", _md(tabd, "config"), ""]
    rt = r[r["metric"] == "runtime_s"]["value"]
    if len(rt):
        md += [f"Run time: {float(rt.max()):.1f} s per run."]
    text = "\n".join(md) + "\n"
    (out_dir / "jiang_fg.md").write_text(text)
    return text
