"""dslearn-bench's workload items run (in-process, at the smallest sizes) and return the figures they name."""

from __future__ import annotations

import argparse
import math

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
