r"""Schema of task ``braga_tbn`` (Braga et al.: distributed online EM, RBPFs, consensus on statistics).

Keys and types are checked by Hydra at composition (``conf/task/braga_tbn.yaml`` is linked to the study's
settings, :class:`dslearn.studies.braga_tbn.BragaTask`), ranges and choices by the field rules, and
:func:`check` holds the rules that need several fields or built objects: the noise parameters (K modes, pi
rows sum to 1, the true and initial K agree), a connected finger-four graph, the consensus weights (Eq. 22),
the strategy names, the terrain resolution and the steady-state window against the flight duration.

``task.consensus.weights``: ``half_max_degree`` (the paper's Eq. 26, 1/(2 d_max)), ``max_degree_core``
(1/(1 + d_max), :func:`dslearn.fusion.weights.max_degree`), ``metropolis`` or ``matrix``. The former
value ``max_degree`` (which meant 1/(2 d_max) here but 1/(1 + d_max) in :mod:`dslearn.fusion.weights`)
is refused with a message naming both replacements.
"""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from dslearn.errors import ConfigError
from dslearn.fusion.statistics import network_adjacency, parse_strategy, weight_matrix
from dslearn.models.jmnls import make_params
from dslearn.schemas.base import register_task
from dslearn.studies.braga_tbn import BragaTask


def check(cfg: DictConfig) -> None:
    """The cross-field rules of ``cfg.task`` (after the field rules); raises :class:`ConfigError`."""
    t = OmegaConf.to_container(cfg.task, resolve=True)
    m = t["modes"]
    truth = make_params(m["mu_true"], m["sigma_true"], m["pi_true"],
                        prefix="task.modes (true: mu_true/sigma_true/pi_true)")
    init = make_params(m["mu_init"], m["sigma_init"], m["pi_init"],
                       prefix="task.modes (initial: mu_init/sigma_init/pi_init)")
    if truth.k != init.k:
        raise ConfigError(f"task.modes: K mismatch between the true parameters (K={truth.k}) and the initial "
                          f"guess (K={init.k})")
    tr = t["terrain"]
    if tr["resolution_m"] * 4 > tr["size_m"]:
        raise ConfigError(f"task.terrain.resolution_m={tr['resolution_m']} must be much smaller than "
                          f"task.terrain.size_m={tr['size_m']} (at most a quarter)")
    adj = network_adjacency(4, t["network"]["edges"])  # finger four: 4 aircraft
    weight_matrix(adj, t["consensus"]["weights"], t["consensus"]["matrix"])
    for sname in t["strategies"]:
        parse_strategy(sname)
    if len(set(t["strategies"])) != len(t["strategies"]):
        raise ConfigError(f"task.strategies={t['strategies']} has duplicates")
    if t["steady_state_s"] > t["steps"] * t["dt"]:
        raise ConfigError(f"task.steady_state_s={t['steady_state_s']} exceeds the flight duration "
                          f"task.steps * task.dt = {t['steps'] * t['dt']} s")


#: what the study uses in place of each root group (it reads none of them: every part is in ``task``)
INSTEAD = {
    "scenario": "its flights are task.steps, task.dt, task.start and task.formation_spacing over task.terrain",
    "network": "its network is task.network",
    "model": "its motion model is task.process_noise with the terrain modes task.modes",
    "observation": "its measurement model is the terrain map task.terrain with task.modes",
    "consensus": "its fusion is task.consensus with task.strategies",
    "filter": "its filter is the RBPF of task.num_particles, task.resampling and task.em",
    "data": "its Monte Carlo runs are task.mc_runs",
}

register_task("braga_tbn", BragaTask, check, uses=(), instead=INSTEAD)
