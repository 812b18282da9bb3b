"""dslearn/filters/information.py: the chi-square gate's probability range, its degrees of freedom (the
measurement dimension), the inclusive boundary and the counts it records (benchmarks/mutation:
survivors of the mutation run)."""

import math

import pytest
import torch

from dslearn.diagnostics import Diagnostics
from dslearn.filters.information import chi2_quantile, novel_information
from dslearn.models import LinearPositionObservation

D = torch.float64


@pytest.mark.parametrize("dof", [2, 3])
@pytest.mark.parametrize("prob", [0.0, 1.0, 1.5, -0.1])
def test_gate_probability_outside_the_open_unit_interval_is_refused(prob, dof):
    with pytest.raises(ValueError, match=rf"gate probability {prob!r} must be in \(0, 1\)"):
        chi2_quantile(prob, dof)


def test_chi2_quantiles_closed_form_and_scipy():
    assert chi2_quantile(0.99, 2) == pytest.approx(9.210340371976184, rel=1e-14)
    assert chi2_quantile(0.99, 1) == pytest.approx(6.634896601021214, rel=1e-12)
    assert chi2_quantile(0.99, 3) == pytest.approx(11.344866730144373, rel=1e-12)


def _gate(errors, prob=0.99):
    """One node, one episode, ``len(errors)`` targets at the origin; R = I, so the gate statistic is
    |z|^2. Returns the kept mask and the counts recorded."""
    a = len(errors)
    y = torch.zeros(1, 1, 4 * a, dtype=D)
    meas = torch.tensor(errors, dtype=D).view(1, 1, a, 2)
    vis = torch.ones(1, 1, a, dtype=torch.bool)
    with Diagnostics() as d:
        dq, do = novel_information(y, meas, vis, LinearPositionObservation(1.0), gate_prob=prob)
    kept = do.diagonal(dim1=-2, dim2=-1).view(a, 4)[:, 0] > 0
    return kept.tolist(), (d.gate_tested, d.gate_rejected)


def test_gate_uses_the_measurement_dimension_and_counts_the_rejected():
    """2-D measurements: chi2_2(0.99) = 9.21. |z|^2 = 8 passes (it would fail with 1 dof, 6.63),
    |z|^2 = 10 fails (it would pass with 3 dof, 11.34), 0.25 passes: 3 tested, 1 rejected."""
    kept, counts = _gate([[2.0, 2.0], [3.0, 1.0], [0.5, 0.0]])
    assert kept == [True, False, True]
    assert counts == (3, 1)


def test_gate_boundary_is_inclusive():
    """nu^T S^-1 nu <= chi2(p): a measurement exactly on the threshold (|z|^2 = 4 = -2 log(1 - p)) is kept."""
    p = -math.expm1(-2.0)
    assert chi2_quantile(p, 2) == 4.0
    kept, counts = _gate([[2.0, 0.0], [0.0, -2.0], [2.0, 1e-7]], prob=p)
    assert kept == [True, True, False] and counts == (3, 1)
