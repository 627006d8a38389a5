"""Shared base for every config section: unknown keys are errors, values are checked."""

from __future__ import annotations

import json
from collections.abc import Iterable
from typing import Any

from pydantic import BaseModel, ConfigDict


class Section(BaseModel):
    """A config table. ``extra="forbid"`` turns a typo in the TOML into a named error."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, frozen=False)


class OptionalPart(Section):
    """A table for a part the machine may or may not have (GNSS, MQTT, CAN, ...).

    One rule for all of them, so that no part is ever off without a word: a table present in
    the file (or created by an environment override such as ``SOWGATE_MQTT__HOST``) switches
    its part on unless it says ``enabled = false``; a table absent leaves the part at its
    default, which is off except for paper A's RS485 bus and screen. ``Settings`` applies the
    rule (``switch_on_present_parts``) because only it can tell an absent table from an empty
    one; a section built directly in code keeps the default of its ``enabled`` field.
    """

    enabled: bool = False


def switch_on_present_parts(data: dict[str, Any], parts: Iterable[str]) -> dict[str, Any]:
    """``data`` with ``enabled = true`` added to every present part table that has no
    ``enabled`` key of its own. Tables given as already-built sections are left as they are."""
    for name in parts:
        table = data.get(name)
        if isinstance(table, dict) and "enabled" not in table:
            data = {**data, name: {**table, "enabled": True}}
    return data


def source_chain(value: Any) -> Any:
    """A priority list of sources, also written as one string ``"a_then_b_then_c"``.

    ``"isobus_then_gnss"`` and ``["isobus", "gnss"]`` mean the same: the first source with a
    fresh value wins, the next ones are the fallback. Anything else is left for pydantic to
    reject with the allowed names.
    """
    if isinstance(value, str):
        text = value.strip()
        if text.startswith("["):  # a list given as JSON (environment override)
            try:
                return json.loads(text)
            except json.JSONDecodeError:
                return value
        return [part.strip() for part in text.split("_then_")]
    return value


def check_unique(value: list[str]) -> list[str]:
    dupes = sorted({v for v in value if value.count(v) > 1})
    if dupes:
        raise ValueError(f"each source may appear once (repeated: {', '.join(dupes)})")
    return value


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
