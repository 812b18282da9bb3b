import pytest
import torch

from dslearn.fusion.weights import consensus_weights, max_degree, metropolis, uniform, validate_weights
from dslearn.errors import ConfigError
from dslearn.network import adjacency_from_edges, is_connected
from dslearn.sim.placement import make_network


def ring(n):
    return adjacency_from_edges(n, [[i, (i + 1) % n] for i in range(n)] + [[0, 2]])


# ring(7) by hand: edges 0-1, 1-2, ..., 6-0 and the chord 0-2; degrees 3, 2, 3, 2, 2, 2, 2 (d_max = 3)
_q, _t = 1 / 4, 1 / 3
RING7 = {
    # Metropolis 1 / (1 + max(d_i, d_j)): 1/4 on an edge touching node 0 or 2, else 1/3; the rest on the diagonal
    metropolis: [[_q, _q, _q, 0, 0, 0, _q], [_q, 1 / 2, _q, 0, 0, 0, 0], [_q, _q, _q, _q, 0, 0, 0],
                 [0, 0, _q, 5 / 12, _t, 0, 0], [0, 0, 0, _t, _t, _t, 0], [0, 0, 0, 0, _t, _t, _t],
                 [_q, 0, 0, 0, 0, _t, 5 / 12]],
    # maximum degree 1 / (1 + 3) on every edge, 1 - d_i / 4 on the diagonal
    max_degree: [[_q, _q, _q, 0, 0, 0, _q], [_q, 1 / 2, _q, 0, 0, 0, 0], [_q, _q, _q, _q, 0, 0, 0],
                 [0, 0, _q, 1 / 2, _q, 0, 0], [0, 0, 0, _q, 1 / 2, _q, 0], [0, 0, 0, 0, _q, 1 / 2, _q],
                 [_q, 0, 0, 0, 0, _q, 1 / 2]],
}


@pytest.mark.parametrize("fn", [metropolis, max_degree])
def test_doubly_stochastic(fn):
    w = fn(ring(7))
    torch.testing.assert_close(w, torch.tensor(RING7[fn], dtype=w.dtype), rtol=0, atol=1e-15)
    assert torch.allclose(w.sum(0), torch.ones(7, dtype=w.dtype), atol=1e-12)
    assert torch.allclose(w.sum(1), torch.ones(7, dtype=w.dtype), atol=1e-12)
    assert torch.allclose(w, w.T)


def test_uniform_row_stochastic_not_doubly():
    adj = ring(7)
    w = uniform(adj)
    assert torch.allclose(w.sum(1), torch.ones(7, dtype=w.dtype), atol=1e-12)
    deg = adj.sum(1)
    assert float(w[0, 0]) == pytest.approx(1.0 / (int(deg[0]) + 1))
    assert not torch.allclose(w.sum(0), torch.ones(7, dtype=w.dtype))
    with pytest.raises(ConfigError, match="doubly"):
        validate_weights(w, adj, doubly=True)


def test_weights_only_on_edges():
    adj = ring(6)
    for m in ("uniform", "metropolis", "max_degree"):
        w = consensus_weights(adj, m)
        off = ~(adj | torch.eye(6, dtype=torch.bool))
        assert (w[off] == 0).all()
    with pytest.raises(ConfigError, match="consensus.weights"):
        consensus_weights(adj, "bogus")


def test_disconnected_network_is_an_error():
    with pytest.raises(ConfigError, match="disconnected"):
        make_network(num_sensors=2, num_comm=1, positions=[[0, 0], [1, 0], [9, 9]], comm_radius=2.0)
    assert not is_connected(adjacency_from_edges(4, [[0, 1], [2, 3]]))


def test_random_network_connected_and_reproducible():
    a = make_network(seed=3)
    b = make_network(seed=3)
    assert torch.equal(a.positions, b.positions)
    assert is_connected(a.adjacency)
    assert a.num_nodes == 10 and int(a.is_sensor.sum()) == 4


def test_visibility_only_sensors_in_range():
    net = make_network(num_sensors=1, num_comm=1, positions=[[0, 0], [1, 0]], comm_radius=2.0, sensing_range=1.0)
    vis = net.visible(torch.tensor([[[0.5, 0.0], [3.0, 0.0]]], dtype=torch.float64))
    assert vis.shape == (2, 1, 2)
    assert vis[0, 0].tolist() == [True, False]
    assert not vis[1].any()  # communication-only node
