"""dslearn/fusion/strategies.py: make_fusion's default number of rounds and its refusal naming the key
(benchmarks/mutation: survivors of the mutation run)."""

import pytest
import torch

from dslearn.errors import ConfigError
from dslearn.fusion.strategies import make_fusion
from dslearn.fusion.weights import metropolis


def test_make_fusion_defaults_to_four_rounds():
    adj = torch.tensor([[0, 1, 0], [1, 0, 1], [0, 1, 0]], dtype=torch.bool)
    w = metropolis(adj)
    f = make_fusion("hybrid", w)
    assert f.iterations == 4 and f.omega == 1.0
    torch.testing.assert_close(f.wl, w @ w @ w @ w, rtol=1e-15, atol=1e-15)


def test_unknown_fusion_is_refused_naming_the_key():
    w = torch.eye(3, dtype=torch.float64)
    with pytest.raises(ConfigError, match=r"^consensus\.name='mean' is not allowed; choose one of \['individual'"):
        make_fusion("mean", w)
