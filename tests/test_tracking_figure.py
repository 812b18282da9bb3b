"""The single run's tracking figure: the arrays the Yu study hands the app (``tracks.npz``) by value, and
``tracking.png`` drawn from them (three panels, labelled with units)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import torch

from dslearn.episodes import Estimates
from dslearn.io import ARTIFACTS, TRACKS_FILE, Artifacts, attach_artifact, write_artifacts
from dslearn.metrics.trajectories import nees_band, position_series
from dslearn.reports.tables import mean_std, sig

TEST_EPISODES = 3


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A tiny Yu run (lin model, hybrid fusion, no training, 3 test episodes) through the Python API, the
    beliefs the study evaluated recorded on the side, and its artifacts written as the app writes them."""
    from dslearn import api
    from dslearn.learning.online import OnlineLearner

    study = api.yu_study(model="lin", consensus="hybrid", train_episodes=0, test_episodes=TEST_EPISODES)
    seen = []
    estimate = OnlineLearner.estimate

    def record(self, ep):
        res = estimate(self, ep)
        seen.append(res)
        return res

    mp = pytest.MonkeyPatch()
    mp.setattr(OnlineLearner, "estimate", record)
    try:
        df = study.run()
    finally:
        mp.undo()
    out = tmp_path_factory.mktemp("tracks")
    written = write_artifacts(out, df.attrs.get(ARTIFACTS))
    assert [p.name for p in written] == [TRACKS_FILE]
    test, _ = study.sample()
    return study, df, seen[-1], test, out, dict(np.load(out / TRACKS_FILE))


def test_saved_network_and_truth_by_value(tiny):
    study, _, res, test, _, z = tiny
    net = study.network
    np.testing.assert_array_equal(z["positions"], net.positions.numpy())
    np.testing.assert_array_equal(z["adjacency"], net.adjacency.numpy())
    np.testing.assert_array_equal(z["is_sensor"], net.is_sensor.numpy())
    assert z["sensing_range"] == net.sensing_range and list(z["nodes"]) == list(net.names)
    # test episode 0's true positions: the scenario's own reading of its states
    np.testing.assert_array_equal(z["truth"], study.scenario.positions(test.states)[0].numpy())
    k = study.scenario.steps
    assert z["truth"].shape == (k + 1, 2, 2) and z["mean"].shape == (net.num_nodes, k + 1, 2, 2)
    np.testing.assert_allclose(z["time"], 0.25 * np.arange(1, k + 1), rtol=0, atol=1e-15)
    # every node's estimate of episode 0 and its covariance: the position blocks of info^-1 (numpy's inverse)
    for i in (0, net.num_nodes - 1):
        for a in range(2):
            np.testing.assert_array_equal(z["mean"][i, :, a], res.mean[i, 0, :, 4 * a:4 * a + 2].numpy())
            cov = np.linalg.inv(res.info[i, 0].numpy())[:, 4 * a:4 * a + 2, 4 * a:4 * a + 2]
            np.testing.assert_allclose(z["cov"][i, :, a], cov, rtol=1e-9, atol=1e-12)
    assert (str(z["model"]), str(z["consensus"]), int(z["train_seen"])) == ("lin", "hybrid", 0)


def test_error_over_time_averages_to_the_result_rows(tiny):
    """Mean over steps 1..K of the per-step error (itself a mean over the test episodes) = the mean over
    the test episodes of each node's track_err row: the same quantity, summed in the other order."""
    study, df, _, _, _, z = tiny
    rows = df[df["metric"] == "track_err"].groupby("node", sort=False)["value"].agg(["mean", "count"])
    assert (rows["count"] == TEST_EPISODES).all()
    for i, node in enumerate(z["nodes"]):
        assert z["pos_err"][i].mean() == pytest.approx(rows.loc[str(node), "mean"], rel=1e-12, abs=0)
    assert int(z["episodes"]) == TEST_EPISODES and int(z["nees_dof"]) == 4


def test_nees_by_hand(tiny):
    """One node and step: mean over the test episodes of sum_a e_a^T P_aa^-1 e_a / (2A), P = info^-1."""
    _, _, res, test, _, z = tiny
    node, t = 6, 5
    truth = test.states.numpy()
    vals = []
    for b in range(TEST_EPISODES):
        p = np.linalg.inv(res.info[node, b, t].numpy())
        d2 = 0.0
        for a in range(2):
            e = res.mean[node, b, t, 4 * a:4 * a + 2].numpy() - truth[b, t, 4 * a:4 * a + 2]
            d2 += e @ np.linalg.solve(p[4 * a:4 * a + 2, 4 * a:4 * a + 2], e)
        vals.append(d2 / 4)
    assert z["nees_pos"][node, t - 1] == pytest.approx(np.mean(vals), rel=1e-9)
    err = np.mean([np.mean([np.hypot(*(res.mean[node, b, t, 4 * a:4 * a + 2].numpy() - truth[b, t, 4 * a:4 * a + 2]))
                            for a in range(2)]) for b in range(TEST_EPISODES)])
    assert z["pos_err"][node, t - 1] == pytest.approx(err, rel=1e-12)
    np.testing.assert_allclose(z["nees_band"], nees_band(4, TEST_EPISODES), rtol=1e-15)


def _chi2_cdf_even(x: float, n: int) -> float:
    """CDF of chi-square with an even number n of degrees of freedom (closed form)."""
    m = n // 2
    return 1.0 - math.exp(-x / 2) * sum((x / 2) ** k / math.factorial(k) for k in range(m))


@pytest.mark.parametrize("dof,episodes", [(2, 1), (4, 3), (2, 10)])
def test_nees_band_closed_form(dof, episodes):
    lo, hi = nees_band(dof, episodes)
    n = dof * episodes
    assert _chi2_cdf_even(lo * n, n) == pytest.approx(0.025, abs=1e-10)
    assert _chi2_cdf_even(hi * n, n) == pytest.approx(0.975, abs=1e-10)
    if n == 2:
        assert (lo, hi) == pytest.approx((-math.log(0.975), -math.log(0.025)), rel=1e-12)


def test_position_series_averages_over_episodes_not_nodes():
    g = torch.Generator().manual_seed(3)
    n, b, k, a = 2, 3, 4, 2
    mean = torch.randn(n, b, k + 1, a, 2, generator=g, dtype=torch.float64)
    lower = torch.randn(n, b, k + 1, a, 2, 2, generator=g, dtype=torch.float64).tril()
    cov = lower @ lower.transpose(-1, -2) + 0.1 * torch.eye(2, dtype=torch.float64)
    truth = torch.randn(b, k + 1, a, 2, generator=g, dtype=torch.float64)
    s = position_series(Estimates(mean, cov, ["x", "y"], torch.tensor([True, False])), truth)
    m, c, tr = mean.numpy(), cov.numpy(), truth.numpy()
    for i in range(n):
        for t in range(1, k + 1):
            e = m[i, :, t] - tr[:, t]  # (B, A, 2)
            assert s["pos_err"][i, t - 1] == pytest.approx(np.linalg.norm(e, axis=-1).mean(), rel=1e-12)
            d2 = [sum(e[bb, aa] @ np.linalg.inv(c[i, bb, t, aa]) @ e[bb, aa] for aa in range(a)) / (2 * a)
                  for bb in range(b)]
            assert s["nees_pos"][i, t - 1] == pytest.approx(np.mean(d2), rel=1e-10)


def test_artifacts_survive_copies_and_concatenation(tmp_path):
    """pandas copies and compares a table's attrs: arrays have no truth value, so plain dicts would fail."""
    df = attach_artifact(pd.DataFrame({"metric": ["a"], "value": [1.0]}), "x.npz", {"a": np.arange(3.0)})
    both = pd.concat([df.copy(), df.copy()], ignore_index=True)
    assert isinstance(both.attrs[ARTIFACTS], Artifacts) and both.attrs[ARTIFACTS] is df.attrs[ARTIFACTS]
    attach_artifact(df, "t.csv", pd.DataFrame({"k": [1, 2]}))
    attach_artifact(df, "note.txt", "hello")
    write_artifacts(tmp_path, both.attrs[ARTIFACTS])
    np.testing.assert_array_equal(np.load(tmp_path / "x.npz")["a"], np.arange(3.0))
    assert (tmp_path / "t.csv").read_text() == "k\n1\n2\n" and (tmp_path / "note.txt").read_text() == "hello"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["note.txt", "t.csv", "x.npz"]  # no temporary file left
    with pytest.raises(ValueError, match="plain file name"):
        attach_artifact(df, "../x.npz", {})


def test_significant_digits():
    assert [sig(v) for v in (0.075, 0.30549, 1.2, 0.9996, 12.345, 1234.5, 0.000123, 0, float("nan"))] == [
        "0.0750", "0.305", "1.20", "1.00", "12.3", "1230", "1.23e-04", "0", "-"]
    assert mean_std(0.4, 0.30549) == "0.400 ± 0.305"


def test_tracking_figure_three_labelled_panels(tiny, monkeypatch, tmp_path):
    import dslearn.reports.yu as yu
    from dslearn.report import summarize

    _, df, _, _, out, z = tiny
    drawn = []
    save = yu.save_figure
    monkeypatch.setattr(yu, "save_figure", lambda fig, path: (drawn.append(fig.axes), save(fig, path))[1])
    text = yu.yu_report(df, summarize(df), out)
    png = (out / "tracking.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and "](tracking.png)" in text
    axes = drawn[-1]
    assert len(axes) == 3
    net, err, nees = axes
    assert net.get_title() == "sensor network and tracks (test episode 0)"
    assert (net.get_xlabel(), net.get_ylabel()) == ("x [m]", "y [m]")
    assert err.get_title() == f"position error (mean over {TEST_EPISODES} test episodes)"
    assert (err.get_xlabel(), err.get_ylabel()) == ("time [s]", "position error [m]")
    assert nees.get_title() == f"position NEES / 4 (mean over {TEST_EPISODES} test episodes)"
    assert nees.get_xlabel() == "time [s]" and nees.get_ylabel().startswith("position NEES / 2A")
    # what is drawn: the first sensing node and the first relay, and the sensor average
    names = list(z["nodes"])
    for ax, key in ((err, "pos_err"), (nees, "nees_pos")):
        lines = {ln.get_label(): ln for ln in ax.get_lines()}
        for node in ("sensor1", "comm1"):
            np.testing.assert_array_equal(lines[node].get_ydata(), z[key][names.index(node)])
            np.testing.assert_array_equal(lines[node].get_xdata(), z["time"])
        avg = next(ln for lab, ln in lines.items() if lab.startswith("sensor average"))
        np.testing.assert_allclose(avg.get_ydata(), z[key][z["sensing"]].mean(0), rtol=1e-15)
    band = [p for p in nees.patches if p.get_label().startswith("95 % band")]
    assert len(band) == 1
    y0, y1 = band[0].get_y(), band[0].get_y() + band[0].get_height()
    np.testing.assert_allclose((y0, y1), z["nees_band"], rtol=1e-12)
    # the true tracks in the network panel are episode 0's truth
    true = [ln for ln in net.get_lines() if ln.get_label() == "true track"]
    np.testing.assert_array_equal(true[0].get_xydata(), z["truth"][:, 0])
