"""dslearn/filters/ekf_fg.py: a prediction passed in is the one refined; the observation variance's
default mode is the paper's CRLB (benchmarks/mutation: survivors of the mutation run)."""

import torch

from dslearn.filters.ekf_fg import TrackState, ekf_fg_step, observation_variance

D = torch.float64


def test_step_refines_the_prediction_passed_in():
    """Eq. 18 and 19 by hand, scalar per parameter, with a prediction that is not Eq. 17's."""
    st = TrackState(torch.tensor([1.0, 2.0], dtype=D), torch.tensor([0.5, 0.2], dtype=D),
                    torch.tensor([0.1, -0.3], dtype=D), torch.tensor([0.05, 0.1], dtype=D))
    obs, ov = torch.tensor([1.5, 1.0], dtype=D), torch.tensor([0.25, 0.4], dtype=D)
    xp, pp = torch.tensor([3.0, -1.0], dtype=D), torch.tensor([2.0, 0.6], dtype=D)  # Eq. 17 would give 1.1, 1.7
    out = ekf_fg_step(st, obs, ov, 0.01, 0.02, x_pred=xp, P_pred=pp)
    p = 1 / (1 / pp + 1 / ov)
    x = p * (xp / pp + obs / ov)
    pv, rv = st.v_var + 0.02, p + st.x_var
    v_var = 1 / (1 / pv + 1 / rv)
    for got, want in zip((out.x_mean, out.x_var, out.v_mean, out.v_var), (x, p, v_var * (st.v_mean / pv + (x - st.x_mean) / rv), v_var)):
        torch.testing.assert_close(got, want, rtol=1e-14, atol=1e-14)
    # without a prediction: Eq. 17, x_pred = x + v, P_pred = P_x + P_v + q_x
    own = ekf_fg_step(st, obs, ov, 0.01, 0.02)
    same = ekf_fg_step(st, obs, ov, 0.01, 0.02, x_pred=st.x_mean + st.v_mean, P_pred=st.x_var + st.v_var + 0.01)
    torch.testing.assert_close(own.x_mean, same.x_mean, rtol=1e-15, atol=1e-15)


def test_observation_variance_default_is_the_crlb():
    crlb = torch.tensor([0.3, 0.7], dtype=D)
    m = torch.tensor([[1.0, 2.0, 3.0], [0.0, -1.0, 4.0]], dtype=D)
    var, gated = observation_variance(crlb, m, m + 1.0, m, torch.ones_like(m))
    assert torch.equal(var, crlb[:, None].expand_as(m)) and not gated.any()


def test_a_lone_prediction_half_is_refused():
    """``x_pred`` without ``P_pred`` (or the reverse) is a caller's mistake, not a request to predict anew."""
    import pytest

    st = TrackState(torch.tensor([1.0], dtype=D), torch.tensor([0.5], dtype=D),
                    torch.tensor([0.1], dtype=D), torch.tensor([0.05], dtype=D))
    obs, ov = torch.tensor([1.5], dtype=D), torch.tensor([0.25], dtype=D)
    for half in ({"x_pred": torch.tensor([3.0], dtype=D)}, {"P_pred": torch.tensor([2.0], dtype=D)}):
        with pytest.raises(ValueError, match="both x_pred and P_pred, or neither"):
            ekf_fg_step(st, obs, ov, 0.01, 0.02, **half)
