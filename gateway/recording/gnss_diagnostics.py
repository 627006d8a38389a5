"""``sowgate decode-gnss FILE|-``: what the receiver really sends, one JSON object per line.

A field engineer with a laptop on the receiver's port (or a capture from the daemon's log)
needs to see, line by line, either the decoded fields or the exact reason a line is refused —
with the *same* decoder the daemon runs, so "works in the tool" means "works in the cab".
"""

from __future__ import annotations

import dataclasses
import json
import sys
from collections.abc import Iterable, Iterator
from datetime import UTC, date, datetime, time
from typing import Any, TextIO

from gateway.recording.positioning.gnss_time import correct_week_rollover
from protocol.gnss import GnssEvent, GnssLineDecoder, Rejected
from protocol.nmea import Rmc, Ths
from protocol.unicore import Heading

EXIT_ALL_DECODED = 0
EXIT_SOME_REJECTED = 1
EXIT_NO_INPUT = 2


def _jsonable(value: Any) -> Any:
    if isinstance(value, datetime | date | time):
        return value.isoformat()
    return value


def event_fields(event: GnssEvent) -> dict[str, Any]:
    """The decoded sentence as a flat JSON-able dict, with derived validity where it exists."""
    out: dict[str, Any] = {"type": event.log if isinstance(event, Heading) else event.kind}
    for f in dataclasses.fields(event):
        if f.name != "log":
            out[f.name] = _jsonable(getattr(event, f.name))
    if isinstance(event, Heading):
        out["valid"] = event.valid
        out["quality"] = event.quality
        out["utc"] = event.utc().isoformat()
    elif isinstance(event, Ths):
        out["valid"] = event.valid
    _flag_week_rollover(event, out)
    return out


def _flag_week_rollover(event: GnssEvent, out: dict[str, Any]) -> None:
    """A date 1024·k weeks early (the receiver's GPS week rollover bug) is shown with the
    date the daemon corrects it to, so the tool tells the engineer what the alarm means."""
    if isinstance(event, Heading):
        stamp = event.utc()
    elif isinstance(event, Rmc) and event.date is not None and event.utc is not None:
        stamp = datetime.combine(event.date, event.utc, UTC)
    else:
        return
    corrected, weeks = correct_week_rollover(stamp.timestamp())
    if weeks:
        out["week_rollover_weeks"] = weeks
        out["corrected_utc"] = datetime.fromtimestamp(corrected, UTC).isoformat()


def decode_stream(lines: Iterable[str]) -> Iterator[dict[str, Any]]:
    """One dict per non-blank input line: ``{"line": n, "ok": True, "type": ..., ...}`` or
    ``{"line": n, "ok": False, "reason": key, "error": message}``.

    Noise before a sentence on the same line is reported as a ``warning`` on a line that still
    decodes, because the daemon resynchronises on the start character exactly like this.
    """
    for n, line in enumerate(lines, start=1):
        raw = line.rstrip("\r\n").encode("utf-8", errors="surrogateescape")
        decoder = GnssLineDecoder()
        results = decoder.feed(raw + b"\n")
        if not results:
            continue  # blank line
        events = [r for r in results if not isinstance(r, Rejected)]
        rejects = [r for r in results if isinstance(r, Rejected)]
        if events:
            record: dict[str, Any] = {"line": n, "ok": True, **event_fields(events[0])}
            if rejects:
                record["warning"] = f"{rejects[0].reason}: {rejects[0].detail}"
            if len(events) > 1:  # a line terminator was lost: say so, show the others too
                record["warning"] = (
                    f"{len(events)} sentences on one line (line terminator missing)"
                )
                record["more"] = [event_fields(e) for e in events[1:]]
            yield record
        else:
            last = rejects[-1]  # the sentence itself, after any garbage prefix
            yield {"line": n, "ok": False, "reason": last.reason, "error": last.detail}


def main_decode_gnss(path_or_dash: str, out: TextIO) -> int:
    """Decode a file (or stdin for ``-``) to JSON lines on ``out``.

    Exit 0 when every line decoded, 1 when any line was rejected, 2 when the input cannot
    be read — so a script can tell "receiver sends junk" from "wrong file name".
    """
    try:
        if path_or_dash == "-":
            data = sys.stdin.buffer.read()
        else:
            with open(path_or_dash, "rb") as fh:
                data = fh.read()
    except OSError as exc:
        print(json.dumps({"ok": False, "error": f"cannot read {path_or_dash}: {exc}"}), file=out)
        return EXIT_NO_INPUT
    text = data.decode("utf-8", errors="surrogateescape")
    status = EXIT_ALL_DECODED
    for record in decode_stream(text.split("\n")):
        if not record["ok"]:
            status = EXIT_SOME_REJECTED
        out.write(json.dumps(record) + "\n")
    return status
