"""The examples a newcomer runs (``examples/``): each runs at a small size in a subprocess from an empty
working directory, writes nothing there nor into the examples' folder, and prints numbers that are
finite and that hold by construction (closed forms, identities, independent recomputations)."""

from __future__ import annotations

import importlib.util
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
NUM = r"(-?\d+\.\d+(?:e[-+]\d+)?)"


def _tree(root: Path) -> dict[str, int]:
    return {str(p.relative_to(root)): p.stat().st_size for p in root.rglob("*")
            if p.is_file() and "__pycache__" not in p.parts}


def run_example(script: Path, *args: str, cwd: Path) -> str:
    """Run ``script`` with this interpreter from the empty folder ``cwd``; its stdout. Fails if it
    writes into ``cwd`` or into the examples' folder."""
    before = _tree(EXAMPLES)
    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}
    env.pop("PYTHONPATH", None)  # the installed package only, no repository folder on the path
    out = subprocess.run([sys.executable, str(script), *args], cwd=cwd, env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    assert list(cwd.iterdir()) == [], f"{script.name} wrote into its working directory: {list(cwd.iterdir())}"
    assert _tree(EXAMPLES) == before, f"{script.name} wrote into examples/"
    return out.stdout


# ------------------------------------------------------------------------------------------------
# 1. compare_fusions.py

def test_compare_fusions(tmp_path):
    out = run_example(EXAMPLES / "compare_fusions.py", "--test-episodes", "4", cwd=tmp_path)
    rows = {m[1]: (float(m[2]), float(m[3])) for m in
            re.finditer(rf"^(individual|cm|ci|hybrid|centralized)\s+{NUM}\s+{NUM}\s+\d+\.\d$", out, re.M)}
    assert list(rows) == ["individual", "cm", "ci", "hybrid", "centralized"], out
    assert all(math.isfinite(v) and v > 0 for r in rows.values() for v in r), out
    rmse = {k: v[0] for k, v in rows.items()}
    # every measurement at every node vs own measurements only (the individual nodes lose the targets)
    assert rmse["centralized"] <= rmse["individual"]
    assert rmse["hybrid"] == pytest.approx(rmse["ci"], abs=1.5e-6)  # omega = 1: the same linear averages (6 decimals)
    # the table is the mean of track_rmse over the test episodes and the *sensing* nodes: recomputed here
    from dslearn import api

    df = api.yu_study(model="lin", consensus="individual", train_episodes=2, test_episodes=4, seed=0).run()
    mine = df[(df.metric == "track_rmse") & (df.node_kind == "sensor")]
    assert len(mine) == 4 * 4  # 4 sensors x 4 episodes
    assert rmse["individual"] == pytest.approx(float(mine.value.mean()), abs=5e-7)


# ------------------------------------------------------------------------------------------------
# 2. my_motion_model/

def _my_models():
    spec = importlib.util.spec_from_file_location("examples_my_models", EXAMPLES / "my_motion_model" / "my_models.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_damped_cv_model_values():
    """The example's model: its Jacobian is autograd's, its mean the closed form, damping 0 is LIN."""
    from dslearn.models.constant_velocity import ConstantVelocity
    from dslearn.types import StepContext, agents

    m = _my_models().DampedConstantVelocity(num_agents=3, noise_std=0.2, damping=0.8, speed=1.5)
    ctx = StepContext(dt=0.25)
    x = torch.randn(2, 5, 12, dtype=torch.float64)
    x[0] *= 0.1  # slow velocities, where v / |v| bends
    auto = torch.autograd.functional.jacobian(lambda z: m(z, ctx).sum((0, 1)), x).permute(1, 2, 0, 3)
    assert torch.allclose(m.jacobian(x, ctx), auto, rtol=0, atol=1e-12)
    # speed after one step: (1 - a) |v| + a s |v| / sqrt(|v|^2 + eps^2), heading kept; position: p + dt v
    a, v, y = 0.8 * 0.25, agents(x)[..., 2:], agents(m(x, ctx))
    n = v.norm(dim=-1)
    assert torch.allclose(y[..., 2:].norm(dim=-1), (1 - a) * n + a * 1.5 * n / (n**2 + 1e-6).sqrt(), atol=1e-12)
    heading = torch.linalg.det(torch.stack([v, y[..., 2:]], -1))  # v and v' parallel
    assert torch.allclose(heading, torch.zeros((), dtype=torch.float64), atol=1e-12)
    assert torch.allclose(y[..., :2], agents(x)[..., :2] + 0.25 * v, atol=1e-14)
    assert torch.equal(m.noise_cov(x, ctx), 0.2**2 * torch.eye(12, dtype=torch.float64).expand(2, 5, 12, 12))
    lin = ConstantVelocity(3, 0.2)
    m0 = _my_models().DampedConstantVelocity(num_agents=3, damping=0.0, speed=1.5)
    assert torch.allclose(m0(x, ctx), lin(x, ctx), atol=1e-14)
    assert torch.allclose(m0.jacobian(x, ctx), lin.jacobian(x, ctx), atol=0)


def test_my_motion_model_in_the_matrix(tmp_path):
    out = run_example(EXAMPLES / "my_motion_model" / "run_matrix.py", "--test-episodes", "4", cwd=tmp_path)
    err = float(re.search(r"max abs error (\S+)", out)[1])
    assert err < 1e-7, out
    rows = {m[1]: (m[2], float(m[3]), float(m[4])) for m in
            re.finditer(rf"^(lin|damped_cv|damped_cv k=0)\s+(ekf \S+ hybrid)\s+{NUM}\s+{NUM}$", out, re.M)}
    assert list(rows) == ["lin", "damped_cv", "damped_cv k=0"], out
    assert all(math.isfinite(v) and v > 0 for r in rows.values() for v in r[1:]), out
    assert rows["damped_cv"][0] == rows["damped_cv k=0"][0] == "ekf damped_cv hybrid"  # the user's part ran
    assert rows["lin"][0] == "ekf lin hybrid"
    assert rows["damped_cv k=0"][1:] == pytest.approx(rows["lin"][1:], abs=1.5e-6)  # damping 0 is LIN (6 decimals)
    assert abs(rows["damped_cv"][1] - rows["lin"][1]) > 1e-3  # damping changes the estimates


# ------------------------------------------------------------------------------------------------
# 3. forecast_own_data/

def _cv_on_circle(speed: float, turn: float, dt: float, obs: int = 8, pred: int = 12) -> tuple[float, float]:
    """ADE / FDE of constant velocity on a circle, from sampled positions (not the example's formula)."""
    r = speed / turn
    ang = torch.arange(obs + pred, dtype=torch.float64) * turn * dt
    p = r * torch.stack([ang.cos(), ang.sin()], -1)  # (20, 2)
    k = torch.arange(1, pred + 1, dtype=torch.float64)[:, None]
    cv = p[obs - 1] + k * (p[obs - 1] - p[obs - 2])
    e = (cv - p[obs:]).norm(dim=-1)
    return float(e.mean()), float(e[-1])


def test_forecast_own_data(tmp_path):
    out = run_example(EXAMPLES / "forecast_own_data" / "forecast_own_data.py", "--gp-points", "300", cwd=tmp_path)
    rows = {m[1]: (float(m[2]), float(m[3]), int(m[4])) for m in
            re.finditer(rf"^(cv|gp)\s+{NUM}\s+{NUM}\s+(\d+)$", out, re.M)}
    assert list(rows) == ["cv", "gp"], out
    assert all(math.isfinite(v) for r in rows.values() for v in r), out
    assert rows["cv"][2] == rows["gp"][2] > 0  # the same pedestrian-windows
    ade, fde = _cv_on_circle(1.2, 0.3, 0.4)  # the example's walkers: 1.2 m/s, 0.3 rad/s, 0.4 s per row
    assert rows["cv"][0] == pytest.approx(ade, abs=1e-6) and rows["cv"][1] == pytest.approx(fde, abs=1e-6)
    # the GP learns the turning ([v_t, v_{t-1}] -> v_{t+1}) from plaza_a; constant velocity cannot
    assert rows["gp"][0] < 0.5 * rows["cv"][0] and rows["gp"][1] < 0.5 * rows["cv"][1]
