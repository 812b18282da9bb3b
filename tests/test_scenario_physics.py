"""A scenario's physics reach every method: a matrix cell's method is built with the measurement noise, the time
step, the sensors and the communication graph of the scenario it runs on (the scenario's own network where it
brings one, else the run's ``network`` part), never with a root-group default; also when the scenario's noise or
step is overridden. One preset per method family on every matrix scenario it fits.

What each family is checked on (its parts, then what it hands its engine when it estimates, caught by a spy that
stops the run there):

* the distributed filter (EKF/UKF with LIN, the social force, the GP, the LSTM): the observation model's ``R`` is
  ``meas_std^2 I``; the learner gets the cell's sensors and the scenario's step (``ctx.dt``); the LSTM is built for
  that step; the consensus weights are nonzero exactly on the sensors' graph; ``learner=fg_identification`` gets
  the training episodes' true tracks and the scenario's step;
* Liu's DGPT: its tracker gets the scenario's sensors (one expert each) and step;
* Jiang's FG-EKF: its tracker gets the scenario's sensors and their noise ``sigma_y``;
* the FG-EKF on position sensors: its identification (on the training measurements) and its tracker (on the test
  ones) get the sensors' noise, the scenario's step and area;
* Braga's RBPF: its filters step with the scenario's ``T``, over the scenario's map, and the statistics consensus
  weights are nonzero exactly on the formation's graph;
* the RBPF over noise modes (``rbpf_em_lin``): its filters step with the scenario's ``dt``, the EM's initial modes are
  the learner's multiples of the std of one reading (``meas_std``; Jiang's ``sigma_y / sqrt(L)``, its observation
  model the scenario's sensors and samples), the statistics consensus over the sensors' graph.
"""

from __future__ import annotations

import functools
import types

import pytest
import torch

from dslearn import api
from dslearn.compose import _Slots, build_network
from dslearn.data.ethucy import data_available
from dslearn.episodes import Episodes, Measurements
from dslearn.errors import ConfigError

#: what every matrix scenario declares, by hand from conf/scenario/*.yaml and conf/network/yu.yaml:
#: (sensors' noise sigma, time step [s], nodes, sensing nodes)
PHYSICS = {
    "yu_two_agents": (0.2, 0.25, 10, 4),  # no sensors of its own: the network part (conf/network/yu.yaml)
    "liu_s1": (2.0, 1.0, 200, 200),
    "liu_s2": (2.0, 1.0, 200, 200),
    "liu_s3": (2.0, 1.0, 200, 200),
    "corridor": (0.2, 0.4, 4, 4),
    "eth_zara1": (0.2, 0.4, 4, 4),
    "jiang": (5.0, 1.0, 3, 3),  # sigma_y of one squared-range sample [m^2]
    "braga": (4.0, 0.05, 4, 4),  # the altimeter's largest true mode (the RBPF learns the noise itself)
}
POSITION = ["yu_two_agents", "liu_s1", "liu_s2", "liu_s3", "corridor"] + (["eth_zara1"] if data_available() else [])
#: one preset per method family, on every scenario it fits
CELLS = ([(m, s) for m in ("ekf_lin_hybrid", "ekf_gp_hybrid", "ekf_lstm_hybrid", "dgpt_rbcm") for s in POSITION]
         + [("ukf_sfm_hybrid", "yu_two_agents"), ("fg_ekf", "jiang"), ("rbpf_em", "braga")]
         + [("fg_ekf_lin", s) for s in POSITION])
#: the distributed filter whose motion model the factor-graph identification sets: position sensors and Braga's
CELLS += [("ekf_cv_fg_individual", s) for s in POSITION + ["braga"]]
#: the RBPF over noise modes: every node's Kalman filters on position sensors, a fusion centre's on Jiang's
CELLS += [("rbpf_em_lin", "yu_two_agents"), ("rbpf_em_lin", "liu_s1"), ("rbpf_em_lin", "jiang")]
#: overridden physics: (method, scenario, override, noise, dt) the cell must use instead of the scenario's file
OVERRIDDEN = [
    ("ekf_lin_hybrid", "liu_s1", "scenario.meas_std=0.7", 0.7, 1.0),
    ("ekf_gp_hybrid", "liu_s2", "scenario.meas_std=0.7", 0.7, 1.0),
    ("ekf_lstm_hybrid", "liu_s3", "scenario.dt=0.5", 2.0, 0.5),
    ("dgpt_rbcm", "liu_s1", "scenario.dt=0.5", 2.0, 0.5),
    ("ekf_lin_hybrid", "corridor", "scenario.network.meas_std=0.5", 0.5, 0.4),
    ("ekf_lstm_hybrid", "corridor", "scenario.network.meas_std=0.5", 0.5, 0.4),
    ("ekf_lin_hybrid", "yu_two_agents", "network.meas_std=0.35", 0.35, 0.25),  # its sensors: the network part
    ("ukf_sfm_hybrid", "yu_two_agents", "scenario.dt=0.5", 0.2, 0.5),
    ("fg_ekf", "jiang", "scenario.sigma_y=3.0", 3.0, 1.0),
    ("rbpf_em", "braga", "scenario.dt=0.1", 4.0, 0.1),
    ("rbpf_em_lin", "jiang", "scenario.sigma_y=3.0", 3.0, 1.0),
    ("rbpf_em_lin", "liu_s1", "scenario.meas_std=0.7", 0.7, 1.0),
    ("fg_ekf_lin", "liu_s2", "scenario.meas_std=0.7", 0.7, 1.0),
    ("fg_ekf_lin", "liu_s3", "scenario.dt=0.5", 2.0, 0.5),
    ("fg_ekf_lin", "corridor", "scenario.network.meas_std=0.5", 0.5, 0.4),
    ("fg_ekf_lin", "yu_two_agents", "network.meas_std=0.35", 0.35, 0.25),
    ("ekf_cv_fg_individual", "braga", "scenario.dt=0.1", 4.0, 0.1),
    ("ekf_cv_fg_individual", "liu_s1", "scenario.meas_std=0.7", 0.7, 1.0),
    ("ekf_cv_fg_individual", "corridor", "scenario.network.meas_std=0.5", 0.5, 0.4),
]


class Caught(Exception):
    """Raised by a spy with what the method handed its engine."""

    def __init__(self, **seen):
        super().__init__("caught")
        self.seen = seen


@functools.lru_cache(maxsize=None)
def _cell(method: str, scenario: str, *extra: str):
    """The cell's configuration (validated: the up-front check builds it too) and its parts on the meta device."""
    cfg = api.compose("task=matrix", f"method={method}", f"scenario={scenario}", *extra)
    slots = _Slots(cfg, torch.device("meta"))
    return cfg, slots["scenario"], slots["scenario_network"], slots["method"]


def _zeros(scenario, network, dz: int = 2) -> Measurements:
    """Measurements of the scenario's shape (one episode, all zero, all visible): what the spies need."""
    spec = scenario.spec
    shape = (network.num_nodes, 1, spec.steps + 1, spec.num_agents)
    return Measurements(torch.zeros(*shape, dz, dtype=torch.float64), torch.ones(shape, dtype=torch.bool))


def _graph(weights: torch.Tensor) -> torch.Tensor:
    """The communication graph a consensus weight matrix uses: its nonzero off-diagonal entries."""
    w = torch.as_tensor(weights) != 0
    return w & ~torch.eye(w.shape[0], dtype=torch.bool)


def _check_sensors(cfg, scenario, net, noise: float, dt: float, nodes: int, sensing: int):
    """The cell's sensors: the scenario's own (the very object) where it has one, else the network part's placement;
    with the given noise, step and sizes."""
    if scenario.network is not None:
        assert net is scenario.network
    else:
        placed = build_network(cfg)
        assert torch.equal(net.positions, placed.positions) and torch.equal(net.adjacency, placed.adjacency)
    assert net.meas_std == pytest.approx(noise, rel=1e-12)
    assert (net.num_nodes, net.num_sensors) == (nodes, sensing)
    assert scenario.spec.dt == pytest.approx(dt, rel=1e-12) and scenario.ctx().dt == pytest.approx(dt, rel=1e-12)


def _check_method(monkeypatch, scenario, net, method, noise: float, dt: float):
    """What the built method uses, family by family (see the module's docstring)."""
    from dslearn.methods import dgpt as dgpt_mod, distributed as dist_mod, rbpf as rbpf_mod
    from dslearn.methods.dgpt import DGPTMethod
    from dslearn.methods.distributed import DistributedFilter
    from dslearn.methods.factor_graph import FactorGraphMethod, FactorGraphMotionMethod
    from dslearn.methods.rbpf import RBPFMethod
    from dslearn.methods.rbpf_modes import RBPFModesMethod

    if isinstance(method, DistributedFilter):
        r = method.observation.noise_cov(torch.zeros(1, 4, dtype=torch.float64))[0]
        dz = method.observation.meas_dim  # 2 position readings, 1 altitude (Braga's)
        assert torch.allclose(r, noise**2 * torch.eye(dz, dtype=torch.float64), rtol=1e-12, atol=0.0)
        assert torch.equal(_graph(method.fusion.weights), net.adjacency)
        assert method.fusion.weights.shape == (net.num_nodes, net.num_nodes)
        if hasattr(method.model, "dt"):  # the LSTM: built for the scenario's step
            assert method.model.dt == pytest.approx(dt, rel=1e-12)

        def spy(network, model, obs, fusion, ctx, **kw):
            raise Caught(network=network, obs=obs, ctx=ctx)

        monkeypatch.setattr(dist_mod, "OnlineLearner", spy)
        with pytest.raises(Caught) as got:
            method.estimate(scenario, net, None, _zeros(scenario, net), 0)
        seen = got.value.seen
        assert seen["network"] is net and seen["obs"] is method.observation
        assert seen["ctx"].dt == pytest.approx(dt, rel=1e-12)
        if hasattr(method.learner, "fit_motion"):  # learner=fg_identification: the true tracks and the step
            def fit(model, states, step, pos_std, vel_std, seed):
                raise Caught(model=model, states=states, dt=step, prior=(pos_std, vel_std), seed=seed)

            monkeypatch.setattr(dist_mod, "OnlineLearner", lambda *args, **kw: types.SimpleNamespace(learnable=False))
            monkeypatch.setattr(method.learner, "fit_motion", fit)
            test = _zeros(scenario, net)
            train = Episodes(torch.zeros(1, scenario.spec.steps + 1, 4 * scenario.spec.num_agents,
                                         dtype=torch.float64), test.meas, test.visible)
            with pytest.raises(Caught) as got:
                method.estimate(scenario, net, train, test, 3)
            seen = got.value.seen
            assert seen["model"] is method.model and seen["states"] is train.states and seen["seed"] == 3
            assert seen["dt"] == pytest.approx(dt, rel=1e-12)
            assert seen["prior"] == (method.prior_pos_std, method.prior_vel_std)
    elif isinstance(method, DGPTMethod):
        def spy(z, vis, window, **kw):
            raise Caught(z=z, dt=kw["dt"])

        monkeypatch.setattr(dgpt_mod, "track", spy)
        with pytest.raises(Caught) as got:
            method.estimate(scenario, net, None, _zeros(scenario, net), 0)
        assert got.value.seen["z"].shape[1] == net.num_sensors  # one expert per sensor of the cell
        assert got.value.seen["dt"] == pytest.approx(dt, rel=1e-12)
    elif isinstance(method, FactorGraphMethod):
        def spy(h, samples, sigma_y):
            raise Caught(h=h, samples=samples, sigma_y=sigma_y)

        monkeypatch.setattr(method, "track", spy)
        with pytest.raises(Caught) as got:
            method.estimate(scenario, net, None, _zeros(scenario, net, scenario.num_samples), 0)
        seen = got.value.seen
        assert seen["sigma_y"] == pytest.approx(noise, rel=1e-12)
        assert torch.equal(seen["h"].sensors, scenario.sensors) and seen["samples"].shape[2] == net.num_sensors
    elif isinstance(method, FactorGraphMotionMethod):
        learned = {}

        def learn(train, sigma, dt, area):
            learned.update(train=train, sigma=sigma, dt=dt, area=area)
            return types.SimpleNamespace(theta=torch.tensor([1.0, 0.0], dtype=torch.float64))

        def track(test, theta, sigma, dt, area):
            raise Caught(test=test, theta=theta, sigma=sigma, dt=dt, area=area)

        monkeypatch.setattr(method, "learn", learn)
        monkeypatch.setattr(method, "track", track)
        test = _zeros(scenario, net)
        train = Episodes(torch.zeros(1, scenario.spec.steps + 1, 4 * scenario.spec.num_agents, dtype=torch.float64),
                         test.meas, test.visible)
        with pytest.raises(Caught) as got:
            method.estimate(scenario, net, train, test, 0)
        seen = got.value.seen
        for part in (learned, seen):  # the identification and the tracker: the cell's sensors' noise, step, area
            assert part["sigma"] == pytest.approx(noise, rel=1e-12) and part["dt"] == pytest.approx(dt, rel=1e-12)
            assert tuple(part["area"]) == tuple(scenario.area)
        assert learned["train"].meas is train.meas and seen["test"] is test and seen["theta"].tolist() == [1.0, 0.0]
        assert test.meas.shape[0] == net.num_nodes  # every node's measurements reach it (the fusion centre's)
    elif isinstance(method, RBPFMethod):
        assert torch.equal(_graph(method.fusion.weights), net.adjacency)

        def spy(y, terrain, x0, strategies, weights, init, dyn, **kw):
            raise Caught(terrain=terrain, dyn=dyn, weights=weights)

        monkeypatch.setattr(rbpf_mod, "run_tbn", spy)
        with pytest.raises(Caught) as got:
            method.estimate(scenario, net, None, _zeros(scenario, net), 0)
        seen = got.value.seen
        assert seen["dyn"].F[0, 2].item() == pytest.approx(dt, rel=1e-12)  # x += T vx (Eq. 23)
        assert seen["weights"] is method.fusion.weights
        assert torch.equal(seen["terrain"].z, scenario.terrain.z.to(seen["terrain"].z))
    elif isinstance(method, RBPFModesMethod):
        from dslearn.methods import rbpf_modes as modes_mod

        assert method.fusion.weights.shape == (net.num_nodes, net.num_nodes)
        assert torch.equal(_graph(method.fusion.weights), net.adjacency)
        sigma_init = method.learner.init.sigma.to(torch.float64)
        if method.centre:  # Jiang's squared ranges: one reading is the mean of the scenario's L samples
            obs = method.observation
            assert obs.noise_std == pytest.approx(noise, rel=1e-12) and obs.samples == scenario.num_samples
            assert obs.sensors.shape == scenario.sensors.shape
            reading = noise / scenario.num_samples ** 0.5
            b, a = 1, scenario.spec.num_agents
            monkeypatch.setattr(method, "centre_prior", lambda *args: (
                torch.zeros(b, a, 4, dtype=torch.float64), torch.eye(4, dtype=torch.float64).expand(b, a, 4, 4)))

            def spy(state, y, visible, model, observe, theta, gen, **kw):
                raise Caught(theta=theta, model=model)

            monkeypatch.setattr(modes_mod, "mkf_step_sensors", spy)
            meas = _zeros(scenario, net, scenario.num_samples)
        else:
            reading = noise

            def spy(state, y, visible, model, theta, gen, **kw):
                raise Caught(theta=theta, model=model)

            monkeypatch.setattr(modes_mod, "mkf_step", spy)
            meas = _zeros(scenario, net)
        with pytest.raises(Caught) as got:
            method.estimate(scenario, net, None, meas, 0)
        seen = got.value.seen
        assert seen["model"].F[0, 2].item() == pytest.approx(dt, rel=1e-12)  # x += dt vx
        sig = seen["theta"].sigma  # the noise the method uses: (B, 1, S, K) at the centre, (B, S, 1, K) per node
        sig = sig.reshape(-1, sig.shape[-1])
        assert sig.shape[0] == net.num_nodes  # every sensor's (node's) own modes
        torch.testing.assert_close(sig, (reading * sigma_init).expand(sig.shape), rtol=1e-12, atol=0)
    else:  # a new family: extend this test
        raise AssertionError(f"no physics contract for {type(method).__name__}")


def test_the_cells_are_those_that_fit():
    """Every (family, scenario) pair above fits (a cell the matrix runs); the others are refused."""
    from dslearn.schemas.matrix import cell

    for m, s in CELLS:
        assert cell(_cell(m, s)[0]).reason is None, (m, s)
    with pytest.raises(ConfigError, match="does not fit scenario jiang: .*a sensor alone has no position to regress"):
        api.compose("task=matrix", "method=dgpt_rbcm", "scenario=jiang")


@pytest.mark.parametrize("method,scenario", CELLS, ids=[f"{m}-{s}" for m, s in CELLS])
def test_a_cell_uses_its_scenarios_physics(monkeypatch, method, scenario):
    cfg, sc, net, m = _cell(method, scenario)
    noise, dt, nodes, sensing = PHYSICS[scenario]
    _check_sensors(cfg, sc, net, noise, dt, nodes, sensing)
    _check_method(monkeypatch, sc, net, m, noise, dt)


@pytest.mark.parametrize("method,scenario,override,noise,dt", OVERRIDDEN,
                         ids=[f"{m}-{s}-{o}" for m, s, o, *_ in OVERRIDDEN])
def test_an_overridden_scenario_reaches_the_method(monkeypatch, method, scenario, override, noise, dt):
    """The scenario's noise or step set on the command line reaches the method as it reaches the simulated data."""
    cfg, sc, net, m = _cell(method, scenario, override)
    _, _, nodes, sensing = PHYSICS[scenario]
    _check_sensors(cfg, sc, net, noise, dt, nodes, sensing)
    _check_method(monkeypatch, sc, net, m, noise, dt)


def test_a_learned_observation_gp_starts_at_the_sensors_noise():
    """observation=gp (built for real): every node's GP noise variance starts at the cell's sensors' sigma^2."""
    cfg = api.compose("task=matrix", "method=ekf_gp_hybrid", "observation=gp", "scenario=corridor",
                      "scenario.network.meas_std=0.5")
    method = _Slots(cfg)["method"]
    assert torch.allclose(method.observation.gp.noise_var, torch.full((4,), 0.25, dtype=torch.float64),
                          rtol=1e-12, atol=0.0)


def test_an_explicit_observation_noise_is_a_deliberate_mismatch():
    """observation.noise_std=x is kept whatever the sensors' noise (the data still have the scenario's)."""
    _, sc, net, m = _cell("ekf_lin_hybrid", "liu_s1", "observation.noise_std=0.2")
    assert net.meas_std == 2.0 and m.observation.noise_std == 0.2


@pytest.mark.parametrize("task", ["task=yu", "task=matrix"])
def test_a_negative_observation_noise_is_refused(task):
    """null is the sensors' own noise; a number must be > 0, refused up front naming the key."""
    method = ("method=ekf_lin_hybrid",) if task == "task=matrix" else ()
    with pytest.raises(ConfigError, match=r"^observation\.noise_std=-1(\.0)? must be > 0"):
        api.compose(task, *method, "observation.noise_std=-1")


def test_the_yu_study_keeps_its_sensors_noise():
    """task=yu (the root network part, 0.2 m): the observation model's noise is the network's, as before; an explicit
    null is the same."""
    for extra, want in (((), 0.2), (("network.meas_std=0.45",), 0.45), (("observation.noise_std=null",), 0.2),
                        (("observation.noise_std=0.3",), 0.3)):
        assert api.build_study(api.compose("task=yu", *extra)).observation.noise_std == want, extra
