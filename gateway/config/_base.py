"""Shared base for every config section: unknown keys are errors, values are checked."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class Section(BaseModel):
    """A config table. ``extra="forbid"`` turns a typo in the TOML into a named error."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, frozen=False)
