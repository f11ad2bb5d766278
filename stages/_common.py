"""What every stage script stamps its artifacts with (:class:`StageContext`); the options and conventions the
stage scripts share with the user commands live in :mod:`pipeline.cli.conventions` and are handed on here."""

from __future__ import annotations

import dataclasses
from typing import Any, Iterable, Mapping

from pipeline.artifacts.lineage import Meta, make_meta
from pipeline.catalog import STAGES, stage_params
from pipeline.cli.conventions import overwrite_option, stage_code_version, stage_command, teacher_workers_options

__all__ = ["StageContext", "overwrite_option", "stage_code_version", "stage_command", "stage_context",
           "teacher_workers_options"]


@dataclasses.dataclass(frozen=True)
class StageContext:
    """What every artifact of one stage run is stamped with: stage name, code version, declared params."""

    stage: str
    code: str
    params: dict

    def meta(self, schema: str, inputs: Iterable = (), params: Mapping[str, Any] | None = None, **extra) -> Meta:
        """The Meta of one output; ``params`` replaces the declared ones where a stage fingerprints a finer view."""
        return make_meta(schema, self.stage, self.code, self.params if params is None else params, inputs, **extra)


def stage_context(stage: str, stage_file: str, params: Mapping[str, Any]) -> StageContext:
    """The :class:`StageContext` of ``stage`` run by ``stage_file``, with the params the catalogue declares for
    it (what DVC tracks); ``train`` declares none here."""
    declared = stage_params(params, STAGES[stage].params) if stage in STAGES else {}
    return StageContext(stage, stage_code_version(stage_file), declared)
