"""Schema of ``task=yu`` (the synthetic study). The task block names only the study class; its
parts are the root groups (scenario, network, model, observation, consensus, data, filter),
whose schemas and ranges are in :mod:`dslearn.schemas.core`."""

from __future__ import annotations

from dataclasses import dataclass

from dslearn.schemas.base import ROOT_GROUPS, register_task


@dataclass
class YuTask:
    _target_: str = "dslearn.studies.yu.YuStudy"
    name: str = "yu"


#: every root group but the learner and the associator (parts of the matrix's methods): its models learn as they
#: declare (Algorithm 1); each group's option is the part it names, whose declaration of the keys it reads applies
#: (``parts``)
register_task("yu", YuTask, uses=tuple(g for g in ROOT_GROUPS if g not in ("learner", "associator")),
              instead={"learner": "its models learn as they declare: online while tracking (the GPs, Algorithm 1) "
                                  "or offline (the LSTM)"},
              parts=("scenario", "network", "model", "observation", "consensus", "filter"))
