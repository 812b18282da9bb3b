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


register_task("yu", YuTask, uses=ROOT_GROUPS)  # every root group: they are its parts
