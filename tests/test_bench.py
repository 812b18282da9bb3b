"""dslearn-bench's workload items run (in-process, at the smallest sizes) and return the figures they name."""

from __future__ import annotations

import argparse
import math
import os
import re

import pytest

from dslearn import bench


def test_plan_of_the_filters_workload_covers_every_prediction_step_and_the_backprop_epoch():
    a = argparse.Namespace(models="lin", fusions="hybrid", device="cpu")
    items = bench.plan(["filters"], True, a)
    filters = {kw["filter"] for name, kw in items if name == "item_filters"}
    assert filters == {"default", "ukf", "ukf_mm", "adf", "pf"}
    assert {kw["nodes"] for name, kw in items if name == "item_backprop"} == {10, 50}
    assert {kw.get("model", "lin") for name, kw in items if name == "item_backprop"} == {"lin", "sfm", "gp_increment"}
    pf = {(kw["nodes"], kw["particles"]) for name, kw in items if name == "item_filters" and kw["filter"] == "pf"}
    assert pf == {(s, n) for s in (10, 50) for n in (100, 500)}  # nodes x particles


@pytest.mark.parametrize("filt", ["default", "adf"])
def test_item_filters_times_the_step_it_names(filt):
    (row,) = bench.item_filters(filt, nodes=10, steps=4)
    assert row["workload"] == "filters" and row["item"].startswith(f"filter={filt} S=10, 4 steps")
    assert row["wall_s"] > 0 and math.isclose(row["ms_per_step"], 1e3 * row["wall_s"] / 4)
    assert math.isclose(row["ms_per_node_step"], row["ms_per_step"] / 10)


def test_item_filters_sets_the_particle_filters_particles():
    (row,) = bench.item_filters("pf", nodes=10, steps=3, particles=50)
    assert row["item"].startswith("filter=pf particles=50 S=10, 3 steps") and row["wall_s"] > 0


@pytest.mark.parametrize("model", ["sfm", "gp_increment"])
def test_item_backprop_times_the_models_own_parameters(model):
    (row,) = bench.item_backprop(nodes=10, episodes=2, steps=6, epochs=2, model=model)
    assert f"model={model} (" in row["item"] and "model" in row["item"].split("(")[1]
    assert row["reference_s"] > 0 and math.isclose(row["ratio"], row["wall_s"] / row["reference_s"])


def test_item_backprop_compares_an_epoch_with_the_forward_pass():
    (row,) = bench.item_backprop(nodes=10, episodes=2, steps=6, epochs=2)
    assert row["reference_s"] > 0 and math.isclose(row["ratio"], row["wall_s"] / row["reference_s"])


def test_item_network_runs():
    (row,) = bench.item_network(10, steps=3)
    assert row["workload"] == "network" and row["nodes"] == 10 and row["wall_s"] > 0


def test_matrix_settings_parse_the_cells_and_refuse_bad_values():
    from dslearn.errors import ConfigError

    m = bench.matrix_settings(["methods=[ekf_lin_hybrid,dgpt_rbcm]", "scenarios=liu_s1", "train=2", "test=1"])
    assert m == {"methods": ["ekf_lin_hybrid", "dgpt_rbcm"], "scenarios": ["liu_s1"], "train": 2, "test": 1, "seed": 0,
                 "cache": "fresh"}
    assert bench.matrix_settings([]) == bench.MATRIX_DEFAULTS
    a = argparse.Namespace(matrix=m, matrix_cache_dir="CACHE")
    items = bench.plan(["matrix"], False, argparse.Namespace(models="lin", fusions="hybrid", **vars(a)))
    assert [(kw["method"], kw["scenario"], kw["cache_dir"]) for _, kw in items] == [
        ("ekf_lin_hybrid", "liu_s1", "CACHE"), ("dgpt_rbcm", "liu_s1", "CACHE")]
    for tok, says in (("method=[x]", "matrix.method: unknown setting; allowed: methods, scenarios"),
                      ("methods=[nope]", "matrix.methods='[nope]': unknown nope; allowed: adf_gp_hybrid"),
                      ("scenarios=[]", "matrix.scenarios='[]': empty"),
                      ("test=0", "matrix.test='0' must be an integer >= 1"),
                      ("cache=on", "matrix.cache='on': allowed: fresh, off, user")):
        with pytest.raises(ConfigError, match="^" + re.escape(says)):
            bench.matrix_settings([tok])


def test_bench_cli_refuses_a_bad_matrix_setting(capsys):
    with pytest.raises(SystemExit) as e:
        bench.main(["matrix", "train=-1", "--out", "unused"])
    assert e.value.code == 2 and "matrix.train='-1' must be an integer >= 0" in capsys.readouterr().err


def test_item_matrix_times_the_parts_of_a_cell_and_the_second_fit_loads(tmp_path):
    small = ("model.epochs=2", "model.embed=8", "model.hidden=8", "model.pred_len=3")
    kw = dict(train=2, test=1, cache_dir=str(tmp_path), overrides=small)
    before = os.environ["DSLEARN_CACHE_DIR"]
    (first,) = bench.item_matrix("ekf_lstm_hybrid", "yu_two_agents", **kw)
    (second,) = bench.item_matrix("ukf_lstm_hybrid", "yu_two_agents", **kw)
    assert (first["fit_cache"], second["fit_cache"]) == ("fitted, stored", "loaded")
    assert first["offline_fit_s"] > 0 and first["online_learn_s"] == 0 and first["estimate_s"] > 0
    for row in (first, second):
        parts = row["offline_fit_s"] + row["online_learn_s"] + row["estimate_s"]
        assert row["draw_s"] > 0 and 0 < parts <= row["cell_s"] + 1e-6 and row["peak_mb"] >= row["base_mb"] > 0
        assert math.isclose(row["wall_s"], row["build_s"] + row["draw_s"] + row["cell_s"])
    (gp,) = bench.item_matrix("ekf_gp_hybrid", "yu_two_agents", train=1, test=1, cache_dir="off")
    assert gp["fit_cache"] == "" and gp["online_learn_s"] > 0 and gp["offline_fit_s"] == 0
    (dgpt,) = bench.item_matrix("dgpt_rbcm", "yu_two_agents", train=1, test=1, cache_dir="off")
    assert dgpt["cell_s"] > 0 and math.isnan(dgpt["estimate_s"]) and math.isfinite(dgpt["rmse"])
    assert os.environ["DSLEARN_CACHE_DIR"] == before  # the item's cache folder was for its cell only
