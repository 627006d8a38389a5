"""``[agopengps]``: AgOpenGPS (through AgIO) as a speed, work-state and section source.

AgIO broadcasts every AgOpenGPS frame to UDP 8888 on the tractor LAN and forwards what modules
send to its port 9999 (docs/agopengps.md). ``sections`` maps AgOpenGPS's sections (in order:
the first entry is section 1) to the CAN channel they switch and the rows they cover.
"""

from __future__ import annotations

import ipaddress
import re
from typing import Literal

from pydantic import Field, field_validator

from gateway.config._base import OptionalPart, Section

_HOST_PORT = re.compile(r"^\[?([0-9A-Za-z.:-]+?)\]?:(\d+)$")
AGIO_PORT = 9999
MAX_SECTIONS = 64  # PGN 229


def _host_port(value: str, example: str) -> str:
    match = _HOST_PORT.fullmatch(value.strip())
    if match is None:
        raise ValueError(f"must be HOST:PORT, e.g. {example}")
    try:
        ipaddress.ip_address(match.group(1))
    except ValueError:
        raise ValueError(f"the host must be an IP address (e.g. {example})") from None
    if not 1 <= int(match.group(2)) <= 65535:
        raise ValueError(f"the port must be 1-65535, not {match.group(2)}")
    return value.strip()


def split_host_port(value: str) -> tuple[str, int]:
    host, port = value.rsplit(":", 1)
    return host.strip("[]"), int(port)


class AgOpenGpsSectionMap(Section):
    """One AgOpenGPS section: the CAN channel it switches and the rows it covers (1-based)."""

    channel: str | None = None  # None: the section only marks its rows
    rows: list[int] = Field(default_factory=list)

    @field_validator("rows")
    @classmethod
    def _rows(cls, value: list[int]) -> list[int]:
        bad = [r for r in value if not 1 <= r <= 512]
        if bad:
            raise ValueError(f"rows are numbered from 1 (got {bad})")
        return value


class AgOpenGpsSection(OptionalPart):
    enabled: bool = False
    listen: str = "0.0.0.0:8888"  # where AgIO's broadcast arrives
    # where replies and PGN 221 texts go; None: the address AgIO's frames come from, port 9999.
    # Set, it is also the only address whose frames are obeyed (see docs/agopengps.md).
    agio: str | None = None
    stale_after_s: float = Field(4.0, gt=0, le=30)  # RateController's "connected" is 4 s
    # frames a second obeyed from AgIO; AgOpenGPS sends 5-10 a second of each PGN
    max_frames_per_s: float = Field(100.0, ge=5, le=10_000)
    alarm_text_s: int = Field(5, ge=1, le=60)  # how long AgOpenGPS shows an alarm's text
    sections: list[AgOpenGpsSectionMap] = Field(default_factory=list, max_length=MAX_SECTIONS)
    # curve compensation: channel name -> the half of the tool it feeds; that channel meters
    # at its half's mean ground speed from PGN 229's far-left / far-right tool speeds
    channel_sides: dict[str, Literal["left", "right"]] = Field(default_factory=dict)

    @field_validator("listen")
    @classmethod
    def _listen(cls, value: str) -> str:
        return _host_port(value, "0.0.0.0:8888")

    @field_validator("agio")
    @classmethod
    def _agio(cls, value: str | None) -> str | None:
        return None if value is None else _host_port(value, "192.168.5.10:9999")
