"""dslearn-report for a newcomer: units and labels, the sensor average set apart, the default
figure of any sweep (numbers checked against closed forms), report.md as the file to open."""

import contextlib
import io
import json

import numpy as np
import pandas as pd
import pytest

from dslearn.report import (
    AVG_LABEL,
    console_table,
    figure_data,
    main,
    metric_label,
    metric_unit,
    report,
    summarize,
    swept_keys,
)


def test_units_and_labels():
    assert metric_label("track_err") == "track_err [m]" and metric_label("pred_err") == "pred_err [m]"
    assert metric_label("nees") == "state NEES/Dx" and metric_unit("nees") == "1"
    assert metric_label("ade") == "ade [m]" and metric_label("fde") == "fde [m]"
    assert metric_label("wall_time_s") == "wall_time_s [s]" and metric_label("lost_track_m") == "lost_track_m [m]"
    assert metric_label("gate_reject_frac") == "gate_reject_frac" and metric_unit("gate_reject_frac") == "1"
    assert metric_unit("something") is None and metric_label("something") == "something"


def _yu_like(seeds=(0,), lengthscales=(None,)):
    rows = []
    for ls in lengthscales:
        for seed in seeds:
            for e in range(3):
                for node, kind, base in (("sensor1", "sensor", 1.0), ("sensor2", "sensor", 3.0), ("comm1", "comm", 50.0)):
                    for metric, scale in (("track_err", 1.0), ("nees", 10.0)):
                        r = dict(study="s", task="none", model="gp", consensus="hybrid", node=node, node_kind=kind,
                                 metric=metric, seed=seed, episode=e,
                                 value=scale * (base + 0.1 * e + 0.01 * seed + (0 if ls is None else float(ls))))
                        if ls is not None:
                            r["ov.model.lengthscale"] = ls
                            r["ov.seed"] = seed
                        rows.append(r)
    return pd.DataFrame(rows)


def test_console_table_sets_the_sensor_average_apart():
    text = console_table(summarize(_yu_like()))
    lines = text.splitlines()
    assert lines[0] == "study=s, model=gp, consensus=hybrid"
    assert lines[1].split() == ["node", "track_err", "[m]", "state", "NEES/Dx"]
    assert lines[-1].startswith("state NEES/Dx: the NEES of the whole state") and "position NEES / 2A" in lines[-1]
    lines = lines[:-1]
    body = [ln.split()[0] for ln in lines[3:]]
    assert body[:3] == ["sensor1", "sensor2", "comm1"]
    assert set(lines[-2].replace(" ", "")) == {"-"}  # a rule before the average row
    assert lines[-1].startswith(AVG_LABEL)
    # the papers' Average row: mean of the sensor means (1.1 and 3.1), mean of their stds (0.1)
    assert "2.10 ± 0.100" in lines[-1]  # 3 significant digits
    assert "avg" not in "\n".join(lines[3:])


def test_figure_data_one_seed_error_bars_over_episodes():
    df = _yu_like(lengthscales=(0.5, 2.0))
    df = df[df["seed"] == 0]
    assert swept_keys(df) == ["ov.model.lengthscale"]
    data, over = figure_data(df)
    assert over == "episodes"
    g = data[(data["metric"] == "track_err")].set_index("ov.model.lengthscale")
    # per episode e the sensor average is (1 + 3)/2 + 0.1 e + ls; mean over e = 0,1,2: 2.1 + ls; std 0.1
    for ls in (0.5, 2.0):
        assert g.loc[ls, "mean"] == pytest.approx(2.1 + ls, abs=1e-12)
        assert g.loc[ls, "err"] == pytest.approx(0.1, abs=1e-12)
        assert g.loc[ls, "n"] == 3


def test_figure_data_several_seeds_error_bars_over_seeds():
    df = _yu_like(seeds=(0, 1, 2, 3), lengthscales=(1.0,))
    data, over = figure_data(df)
    assert over == "seeds"
    row = data[data["metric"] == "nees"].iloc[0]
    # per seed: mean over episodes = 10 * (2.1 + 0.01 s + 1); over seeds s = 0..3
    per_seed = [10 * (3.1 + 0.01 * s) for s in range(4)]
    assert row["mean"] == pytest.approx(np.mean(per_seed), abs=1e-12)
    assert row["err"] == pytest.approx(np.std(per_seed, ddof=1), abs=1e-12)
    assert row["n"] == 4


def test_report_writes_figure_and_index(tmp_path):
    df = _yu_like(seeds=(0, 1), lengthscales=(0.5, 1.0, 2.0))
    p = tmp_path / "sweep_results.csv"
    df.to_csv(p, index=False)
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        main([str(p), "--out", str(tmp_path / "rep")])
    text = out.getvalue().splitlines()
    rep = tmp_path / "rep"
    assert text[-2] == f"open first: {rep / 'report.md'}"
    assert text[-1].startswith("wrote: report.md, summary.csv, summary_seeds.csv, tables.md, tables.tex, figure.png, figure_data.csv")
    png = (rep / "figure.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    md = (rep / "report.md").read_text()
    assert md.startswith(f"# dslearn report: {p}\n\nOpen this file first.") and "![" in md and "## Files written" in md
    for f in ("summary.csv", "summary_seeds.csv", "tables.md", "tables.tex", "figure.png", "figure_data.csv"):
        assert f"- `{f}`: " in md and (rep / f).is_file(), f
    tables = (rep / "tables.md").read_text()
    assert "### track_err [m]" in tables and "### state NEES/Dx" in tables
    summary = pd.read_csv(rep / "summary.csv")
    assert "avg" in set(summary["node"])  # machine names stay in the CSV
    fig = pd.read_csv(rep / "figure_data.csv")
    assert sorted(fig["ov.model.lengthscale"].unique()) == [0.5, 1.0, 2.0] and (fig["n"] == 2).all()
    assert err.getvalue() == ""


def test_yu_tables_label_the_average(tmp_path):
    from dslearn.reports.yu import table_tracking, yu_report

    s = summarize(_yu_like())
    tab = table_tracking(s)
    assert list(tab["node"]) == ["sensor1", "sensor2", AVG_LABEL]
    text = yu_report(_yu_like(), s, tmp_path)
    assert "Tracking error [m]" in text and "state NEES/Dx: the NEES of the whole state" in text and "| hybrid | sensor average |" in text


def test_report_of_a_single_run_dir(make_cfg, tmp_path):
    from dslearn.app.record import execute

    execute(make_cfg("model=lin", "data.train_episodes=0", "data.test_episodes=2", "study=unit"), tmp_path / "r")
    assert json.loads((tmp_path / "r" / "meta.json").read_text())["artifacts"] == ["tracks.npz"]
    text = report(tmp_path / "r")
    assert "Table I" in text and "](tracking.png)" in text
    # the study's tracking figure, not the generic figure of one bar per panel
    assert (tmp_path / "r" / "tracking.png").is_file() and not (tmp_path / "r" / "figure.png").exists()
    written = {p.name for p in report.written}
    assert {"report.md", "summary.csv", "tracking.png", "yu_table1.csv", "yu_table1.md"} <= written


def _two_sensor_results():
    """Two sensors, three episodes, one comm node; lin individual and gp_increment hybrid."""
    rows = []
    vals = {  # (model, consensus, omega, metric, node) -> per-episode values
        ("lin", "individual", "-", "track_err", "sensor1"): [0.10, 0.20, 0.60],
        ("lin", "individual", "-", "track_err", "sensor2"): [0.30, 0.30, 0.90],
        ("lin", "individual", "-", "pred_err", "sensor1"): [1.0, 1.2, 1.4],
        ("lin", "individual", "-", "pred_err", "sensor2"): [1.0, 1.2, 1.4],
        ("gp_increment", "hybrid", "one", "track_err", "sensor1"): [0.05, 0.07, 0.09],
        ("gp_increment", "hybrid", "one", "track_err", "sensor2"): [0.06, 0.06, 0.12],
        ("gp_increment", "hybrid", "one", "pred_err", "sensor1"): [0.2, 0.4, 0.9],
        ("gp_increment", "hybrid", "one", "pred_err", "sensor2"): [0.1, 0.3, 0.2],
    }
    for (model, cons, om, metric, node), v in vals.items():
        for ep, x in enumerate(v):
            rows.append(dict(study="t", task="yu", seed=0, model=model, consensus=cons, omega=om,
                             iterations=4 if cons != "individual" else "-", weights="uniform", train_episodes=5,
                             test_episodes=3, train_seen=5, node=node, node_kind="sensor", episode=ep,
                             metric=metric, value=x))
        rows.append({**rows[-1], "node": "comm1", "node_kind": "comm", "value": 99.0})
    return pd.DataFrame(rows)


def test_paper_shaped_cells_by_hand():
    """One cell of Table I and one of Table II against hand computation: the Average row's mean is the mean of
    the sensors' means, its ± the mean of the sensors' sample standard deviations (ddof 1), not the spread of
    the sensor-averaged error (kept as std_of_sensor_avg); communication nodes never enter it."""
    from dslearn.reports.yu import table_prediction, table_tracking

    s = summarize(_two_sensor_results())
    tab = table_tracking(s).set_index(["fusion", "node"])
    # lin individual: sensor1 mean 0.3, std sqrt(((-.2)^2 + (-.1)^2 + .3^2)/2) = sqrt(0.07); sensor2 mean 0.5,
    # std sqrt((.04 + .04 + .16)/2) = sqrt(0.12)
    m = (0.3 + 0.5) / 2
    sd = (np.sqrt(0.07) + np.sqrt(0.12)) / 2
    assert tab.loc[("individual", AVG_LABEL), "lin"] == f"{m:.3f} ± {sd:.3f}" == "0.400 ± 0.305"  # 3 significant digits
    # gp_increment hybrid: sensor1 0.07 ± 0.02, sensor2 0.08 ± sqrt(0.0012) -> 0.075 ± 0.0273
    m = (0.07 + 0.08) / 2
    sd = (0.02 + np.sqrt(((0.06 - 0.08) ** 2 * 2 + 0.04 ** 2) / 2)) / 2
    assert tab.loc[("hybrid (ω=1), L=4", AVG_LABEL), "gp_increment"] == f"{m:.4f} ± {sd:.4f}" == "0.0750 ± 0.0273"
    # the other spread: per-episode sensor average (0.2, 0.25, 0.75) -> std over episodes
    avg_row = s[(s.node == "avg") & (s.model == "lin") & (s.metric == "track_err")].iloc[0]
    assert avg_row["std_of_sensor_avg"] == pytest.approx(np.std([0.2, 0.25, 0.75], ddof=1))
    pred = table_prediction(s).set_index("node")
    # gp_increment con. pred: sensor1 0.5 ± sqrt(0.13), sensor2 0.2 ± 0.1
    m = (0.5 + 0.2) / 2
    sd = (np.sqrt(((0.2 - 0.5) ** 2 + (0.4 - 0.5) ** 2 + (0.9 - 0.5) ** 2) / 2) + 0.1) / 2
    col = [c for c in pred.columns if c.startswith("gp_increment (con.")]
    assert len(col) == 1 and pred.loc[AVG_LABEL, col[0]] == f"{m:.3f} ± {sd:.3f}"
    assert pred.loc[AVG_LABEL, "lin"] == "1.20 ± 0.200"
