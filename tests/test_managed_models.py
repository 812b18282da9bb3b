"""Managed tracks (targets that enter and leave) are predicted one track at a time: a motion model may drive them
where it declares its agents independent (``independent_targets``) and learns nothing along them. The LSTM without
social pooling is such a model: its joint prediction is each agent's alone (block-diagonal Jacobian), so
:func:`~dslearn.association.multitrack.predict_tracks` on the tracks one by one equals the joint prediction."""

from __future__ import annotations

import pytest
import torch

from dslearn import api
from dslearn.association.multitrack import predict_tracks
from dslearn.compose import build_cell_parts
from dslearn.errors import ConfigError
from dslearn.models import ConstantVelocity
from dslearn.models.lstm import SocialLSTM
from dslearn.types import StepContext

DT = 0.25


def test_declared_independence():
    assert ConstantVelocity(2, 0.1).independent_targets
    assert SocialLSTM(2, embed=8, hidden=8, dt=DT, seed=0).independent_targets
    assert not SocialLSTM(2, embed=8, hidden=8, dt=DT, seed=0, pooling="social").independent_targets


def test_lstm_tracks_alone_equal_the_joint_prediction():
    ctx = StepContext(dt=DT)
    joint = SocialLSTM(3, embed=8, hidden=8, dt=DT, seed=1)
    x = torch.tensor([[0.0, 1.0, 1.0, 0.5], [3.0, -1.0, -0.5, 0.2], [0.5, 0.2, 0.8, -1.0]], dtype=torch.float64)
    m, F, Q = joint.linearize(x.reshape(1, -1), ctx)
    blocks = F[0].unflatten(0, (3, 4)).unflatten(-1, (3, 4))  # (3, 4, 3, 4)
    for i in range(3):
        for j in range(3):
            if i != j:
                assert torch.equal(blocks[i, :, j], torch.zeros(4, 4, dtype=F.dtype))  # independent agents
    cov = torch.eye(4, dtype=torch.float64).expand(3, 4, 4) * 0.3
    one = SocialLSTM(1, embed=8, hidden=8, dt=DT, seed=1)  # the same weights (seed), one agent per call
    pm, pc = predict_tracks(x, cov, one, ctx)
    torch.testing.assert_close(pm, m[0].reshape(3, 4), rtol=0, atol=1e-12)
    ref = torch.stack([blocks[i, :, i] @ cov[i] @ blocks[i, :, i].T for i in range(3)]) \
        + Q[0].unflatten(0, (3, 4)).unflatten(-1, (3, 4)).diagonal(dim1=0, dim2=2).permute(2, 0, 1)
    torch.testing.assert_close(pc, ref, rtol=1e-10, atol=1e-12)
    pm3, pc3 = predict_tracks(x, cov, joint, ctx)  # the 3-agent model's one-agent view
    torch.testing.assert_close(pm3, pm, rtol=0, atol=1e-12)
    torch.testing.assert_close(pc3, pc, rtol=1e-10, atol=1e-12)
    assert joint.one_agent().state_dim == 4 and joint.state_dim == 12  # a view: the joint model unchanged
    with pytest.raises(ValueError, match="social pooling"):
        SocialLSTM(2, embed=8, hidden=8, dt=DT, seed=0, pooling="social").one_agent()


def test_managed_tracks_take_the_offline_lstm_not_the_online_gp():
    def parts(*o):
        return build_cell_parts(api.compose("task=matrix", "scenario=yu_crowd_births", *o), check_only=True)

    assert parts("method=ekf_lstm_hybrid_gnn")[2].model.independent_targets
    with pytest.raises(ConfigError, match="nothing learns along managed tracks"):
        parts("method=ekf_gp_hybrid_gnn")
    with pytest.raises(ConfigError, match="predicts each track alone"):
        parts("method=ekf_lstm_hybrid_gnn", "model=social_lstm")
