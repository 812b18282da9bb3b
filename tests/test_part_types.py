"""Parts are chosen by type, never by name (issue 34): no module of the library proper compares a part's ``name``,
``variant`` or ``kind`` with a string; a part declares what it does (a fusion whether it mixes, a learner what it
learns from, a motion model what a gradient learner may train, a prediction step what it differentiates, a
scenario's spec what it tracks), and the declarations are checked here by value."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import torch

import dslearn

ROOT = Path(dslearn.__file__).resolve().parent
#: outside the library proper: the config schemas, the reports, the command line and its apps, the benchmarks
EXCLUDED_DIRS = ("schemas", "reports", "app")
EXCLUDED_FILES = ("report.py", "bench.py", "reference.py", "run.py")
#: the attributes that name a part
PART_NAMES = {"name", "variant", "kind"}


def library_modules() -> list[Path]:
    out = []
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT)
        if rel.parts[0] in EXCLUDED_DIRS or (len(rel.parts) == 1 and rel.name in EXCLUDED_FILES):
            continue
        out.append(path)
    return out


def _names_attr(node: ast.AST) -> bool:
    """``x.name`` / ``x.variant`` / ``x.kind`` or ``getattr(x, "name", ...)``."""
    if isinstance(node, ast.Attribute):
        return node.attr in PART_NAMES
    return (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "getattr"
            and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant) and node.args[1].value in PART_NAMES)


def _is_strings(node: ast.AST) -> bool:
    """A str constant, or a tuple / list / set of str constants."""
    if isinstance(node, ast.Constant):
        return isinstance(node.value, str)
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return bool(node.elts) and all(isinstance(e, ast.Constant) and isinstance(e.value, str) for e in node.elts)
    return False


def _bound_names(scope: ast.AST) -> set[str]:
    """The local names bound from a part's name within ``scope`` (``kind = self.learner.name``)."""
    out = set()
    for node in ast.walk(scope):
        if isinstance(node, ast.Assign) and _names_attr(node.value):
            out |= {t.id for t in node.targets if isinstance(t, ast.Name)}
        elif isinstance(node, (ast.AnnAssign, ast.NamedExpr)) and node.value is not None and _names_attr(node.value) \
                and isinstance(node.target, ast.Name):
            out.add(node.target.id)
    return out


def name_comparisons(source: str, label: str) -> list[str]:
    """``label:line: code`` of every comparison of a part's name with a string in ``source``."""
    tree = ast.parse(source)
    scopes = [tree, *(n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))]
    found = {}
    for scope in scopes:
        bound = _bound_names(scope) if not isinstance(scope, ast.Module) else set()
        for node in ast.walk(scope):
            if not isinstance(node, ast.Compare):
                continue
            sides = [node.left, *node.comparators]
            named = [s for s in sides if _names_attr(s) or (isinstance(s, ast.Name) and s.id in bound)]
            if named and any(_is_strings(s) for s in sides if s not in named):
                found[(node.lineno, node.col_offset)] = f"{label}:{node.lineno}: {ast.get_source_segment(source, node)}"
    return [found[k] for k in sorted(found)]


def test_no_module_of_the_library_compares_a_part_name_with_a_string():
    modules = library_modules()
    assert len(modules) > 50 and ROOT / "methods" / "distributed.py" in modules
    assert ROOT / "run.py" not in modules and not any("schemas" in p.parts for p in modules)
    bad = [hit for path in modules
           for hit in name_comparisons(path.read_text(encoding="utf-8"), str(path.relative_to(ROOT.parent)))]
    assert not bad, "parts are chosen by type or by what they declare, not by name:\n" + "\n".join(bad)


@pytest.mark.parametrize("code", [
    'if self.base.name in ("individual", "centralized"): pass',
    'x = fusion.name not in ["a", "b"]',
    'y = spec.kind == "self"',
    'z = "lin" == params.kind',
    'def f(self):\n    kind = self.learner.name\n    return kind == "offline"',
    'def f(p):\n    step = getattr(p, "name", "ekf")\n    return step in ("ekf", "ukf")',
])
def test_the_scan_finds_a_name_comparison(code):
    assert len(name_comparisons(code, "m.py")) == 1


@pytest.mark.parametrize("code", [
    'x = f"consensus={fusion.name}"',  # a message may mention a part's name
    'x = self.fusion.name == other.name',
    'x = p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)',
    'x = self.train_fusion == "consensus"',  # an option of a part, not a part's name
    'def f(s):\n    kind, q = parse(s)\n    return kind == "centralised"',
])
def test_the_scan_leaves_the_rest(code):
    assert name_comparisons(code, "m.py") == []


# ------------------------------------------------------------------------------------ the declarations, by value
def _pairs(s=3, b=2, d=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(s, b, d, d, generator=g, dtype=torch.float64)
    info = a @ a.transpose(-1, -2) + d * torch.eye(d, dtype=torch.float64)
    return (torch.randn(s, b, d, generator=g, dtype=torch.float64), info,
            torch.randn(s, b, d, generator=g, dtype=torch.float64), info / 2)


@pytest.mark.parametrize("name", ["individual", "ce", "cm", "ci", "hybrid", "centralized"])
def test_a_fusion_mixes_exactly_where_its_consensus_weights_act(name):
    from dslearn.fusion.strategies import make_fusion
    from dslearn.fusion.weights import consensus_weights

    adj = torch.tensor([[0, 1, 0], [1, 0, 1], [0, 1, 0]], dtype=torch.bool)
    f = make_fusion(name, consensus_weights(adj, "metropolis"), iterations=3)
    q_pred, o_pred, dq, do = _pairs()
    nominal = f(q_pred, o_pred, dq, do)
    other = f(q_pred, o_pred, dq, do, wl=torch.full((3, 3), 1 / 3, dtype=torch.float64))
    acts = not all(torch.equal(x, y) for x, y in zip(nominal, other))
    assert f.mixes is acts
    assert f.rounds == (3 if acts else 0)
    assert f.mixes is (name in ("ce", "cm", "ci", "hybrid"))


def test_a_faulty_network_reads_what_its_fusion_declares():
    from dslearn.fusion.faults import FaultyFusion
    from dslearn.fusion.strategies import make_fusion
    from dslearn.fusion.weights import consensus_weights

    adj = torch.tensor([[0, 1, 0], [1, 0, 1], [0, 1, 0]], dtype=torch.bool)
    for name, mixes in (("individual", False), ("hybrid", True)):
        ff = FaultyFusion(make_fusion(name, consensus_weights(adj, "metropolis"), 2), adj, p_link=0.5)
        assert ff.mixes is mixes and ff.rounds == (2 if mixes else 0)
        if not mixes:  # no rounds: no live graph is drawn (begin() is not even needed)
            q_pred, o_pred, dq, do = _pairs()
            assert all(torch.equal(x, y) for x, y in zip(ff(q_pred, o_pred, dq, do), ff.base(q_pred, o_pred, dq, do)))


def test_each_learner_declares_what_it_learns_from():
    from dslearn.learning.learners import LEARNERS

    declared = {k: (c.learns_online, c.fits_offline, c.learns_through_update) for k, c in LEARNERS.items()}
    assert declared == {
        "online": (True, False, False), "offline": (True, True, False), "none": (False, False, False),
        "online_em": (False, False, False), "online_em_sensor": (False, False, False),
        "online_hyperparameters": (False, False, False), "fg_identification": (False, False, False),
        "backprop": (False, False, True), "calibrate": (False, False, True)}


def test_the_allowed_learners_are_named_after_their_classes():
    from dslearn.methods.distributed import allowed_learner_types, allowed_learners
    from dslearn.models.constant_velocity import ConstantVelocity
    from dslearn.models.observation import LinearPositionObservation

    model, obs = ConstantVelocity(2), LinearPositionObservation(0.1)
    assert allowed_learners(model, obs) == tuple(c.name for c in allowed_learner_types(model, obs))
    assert allowed_learners(model, obs)[:1] == ("none",)


def test_each_prediction_step_declares_what_it_differentiates_and_its_noise():
    from dslearn.filters.adf import MomentMatchingPredict
    from dslearn.filters.information import ExtendedPredict, prediction_step
    from dslearn.filters.particle import ParticlePredict
    from dslearn.filters.ukf import UnscentedPredict

    steps = [ExtendedPredict(), UnscentedPredict(), UnscentedPredict(expected_variance=True), ParticlePredict(),
             MomentMatchingPredict()]
    assert {s.name: (s.noise_at_mean, s.differentiates_gp) for s in steps} == {
        "ekf": (True, True), "ukf": (True, True), "ukf_mm": (False, False), "pf": (False, True),
        "adf": (False, False)}
    assert isinstance(prediction_step(None), ExtendedPredict)
    assert prediction_step(steps[3]) is steps[3]


def test_each_motion_model_declares_what_a_gradient_learner_trains():
    from dslearn.learning import backprop as bp
    from dslearn.learning.sfm_fit import FittedSocialForce
    from dslearn.models.constant_velocity import ConstantVelocity, DampedConstantVelocity
    from dslearn.models.social_force import SocialForce

    assert {k: c.kind for k, c in bp.MOTION_PARAMETERS.items()} == {k: k for k in ("lin", "sfm", "gp", "lstm")}
    cv = ConstantVelocity(2)
    assert bp.declared_parameters(cv) is bp.LinearParameters and bp.motion_misfit(cv) is None and bp.takes_q(cv)
    params = bp.motion_parameters(cv, 2, 0.5)
    assert isinstance(params, bp.LinearParameters) and params.always_q
    assert torch.equal(params.f_block, cv.matrix(0.5)[:4, :4])
    damped = DampedConstantVelocity(2)
    assert damped.gradient_parameters is None and bp.takes_q(damped)
    assert bp.motion_misfit(damped) == "DampedConstantVelocity has no differentiable parameters here"
    sfm = SocialForce(((1.0, 0.0), (0.0, 1.0)))
    assert bp.declared_parameters(sfm) is bp.SocialForceParameters and bp.motion_misfit(sfm) is None
    assert not bp.SocialForceParameters.always_q and not bp.GPParameters.takes_q
    fitted = FittedSocialForce(((0.0, 0.0), (0.0, 0.0)))
    assert bp.motion_misfit(fitted).startswith("the fitted social force sets its desired velocities per episode")


def test_a_gp_under_a_step_that_reads_its_own_factor_is_refused():
    from dslearn.filters.adf import MomentMatchingPredict
    from dslearn.filters.ukf import UnscentedPredict
    from dslearn.learning import backprop as bp
    from dslearn.models.gp import GPMotionModel

    gp = GPMotionModel(8, num_nodes=2)
    assert bp.declared_parameters(gp) is bp.GPParameters and not bp.takes_q(gp)
    assert bp.motion_misfit(gp) is None and bp.motion_misfit(gp, UnscentedPredict()) is None
    assert bp.motion_misfit(gp, MomentMatchingPredict()) == "a GP under filter=adf (the GP's steps: ekf|ukf|pf)"
    assert bp.motion_misfit(gp, UnscentedPredict(expected_variance=True)).startswith("a GP under filter=ukf_mm ")


def test_the_scenario_spec_declares_what_it_tracks():
    from dslearn.episodes import KINDS, ScenarioSpec

    for kind in KINDS:
        spec = ScenarioSpec("x", "position", 2, "pv2d", 1.0, 5, kind=kind)
        assert (spec.tracks_targets, spec.navigates_itself) == (kind == "targets", kind == "self")
    assert ScenarioSpec("x", "position", 2, "pv2d", 1.0, 5).tracks_targets


def test_the_optimiser_is_a_typed_choice():
    from dslearn.filters.dgpt import OPTIMISERS
    from dslearn.filters.dgpt.hyperopt import ElementwiseAdam, Optimiser

    assert OPTIMISERS == ("newton", "adam", "sgd")
    theta = torch.zeros(2, 3, dtype=torch.float64)
    grad = torch.ones(2, 3, dtype=torch.float64)
    idx = torch.tensor([0, 1])
    sgd = ElementwiseAdam(theta, lr=0.1, kind="sgd")
    assert sgd.kind is Optimiser.SGD and torch.allclose(sgd.step(theta, grad, idx), theta - 0.1)
    adam = ElementwiseAdam(theta, lr=0.1)
    assert adam.kind is Optimiser.ADAM
    assert torch.allclose(adam.step(theta, grad, idx), theta - 0.1, atol=1e-6)  # Adam's first step: lr * sign
    with pytest.raises(ValueError):
        ElementwiseAdam(theta, lr=0.1, kind="rmsprop")
