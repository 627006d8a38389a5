"""``[farm]``: whose field this is, for the farm software the records go to.

ISO-XML TaskData (``sowgate export --format isoxml``) files a task under a customer, a farm
and a field; a farm management system matches its own records by these names. All optional:
without them the task is exported on its own, which every reader accepts.
"""

from __future__ import annotations

from pydantic import Field

from gateway.config._base import Section


class FarmSection(Section):
    customer: str | None = Field(None, min_length=1, max_length=32)  # ISO-XML CTR B
    farm: str | None = Field(None, min_length=1, max_length=32)  # FRM B
    field: str | None = Field(None, min_length=1, max_length=32)  # PFD C
    field_area_ha: float = Field(0.0, ge=0, le=429_496)  # PFD D (m², required there)
