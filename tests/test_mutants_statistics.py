"""dslearn/fusion/statistics.py: average consensus keeps the statistics' dtype; hop distances mark an
unreachable node -1 (benchmarks/mutation: survivors of the mutation run)."""

import torch

from dslearn.fusion.statistics import average_consensus, hop_distances


def test_average_consensus_mixes_float32_statistics_with_float64_weights():
    a = torch.tensor([[0.5, 0.5, 0.0], [0.25, 0.5, 0.25], [0.0, 0.5, 0.5]], dtype=torch.float64)
    zeta = torch.arange(12, dtype=torch.float32).view(2, 3, 2)
    out = average_consensus(zeta, a, 3)
    want = torch.einsum("sr,brd->bsd", torch.linalg.matrix_power(a, 3), zeta.double())
    assert out.dtype == torch.float32
    torch.testing.assert_close(out.double(), want, rtol=1e-6, atol=1e-6)


def test_hop_distances_path_and_unreachable():
    adj = torch.zeros(5, 5, dtype=torch.bool)
    for i, j in [(0, 1), (1, 2), (3, 4)]:  # 0-1-2 and a separate 3-4
        adj[i, j] = adj[j, i] = True
    d = hop_distances(adj, 0)
    assert d.dtype == torch.long and d.tolist() == [0, 1, 2, -1, -1]
    assert hop_distances(adj.to(torch.int64), 4).tolist() == [-1, -1, -1, 1, 0]
