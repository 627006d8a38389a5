"""Shared base for every config section: unknown keys are errors, values are checked."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class Section(BaseModel):
    """A config table. ``extra="forbid"`` turns a typo in the TOML into a named error."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, frozen=False)


class FieldProblem(ValueError):
    """A check that spans several keys, reported against the one key the fitter should change.

    pydantic files an error raised in a model validator under the whole table ("control: …",
    or "(root): …" for the file); raising this instead lets ``format_validation_error`` print
    ``section.key: problem (got value)`` like any single-field error.
    """

    def __init__(self, key: str, problem: str, value: object) -> None:
        super().__init__(problem)
        self.key = key
        self.problem = problem
        self.value = value
