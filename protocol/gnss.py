"""Bytes from a GNSS receiver's UART to typed sentences, without doing any I/O.

A receiver port carries NMEA (``$``) and Unicore ASCII logs (``#``) interleaved, plus whatever
the line picked up: the tail of a sentence cut by a reconnect, bytes from a baud-rate mismatch,
sentences we do not use. Every line yields either an event or a ``Rejected`` with a reason, and
the reasons are counted, so a flaky cable shows up as numbers instead of as silence.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import Final

from protocol.errors import ChecksumError, FieldError, FrameError, ProtocolError
from protocol.nmea import (
    Gga,
    Hdt,
    MissingFieldError,
    Rmc,
    Ths,
    TruncatedError,
    UnknownSentenceError,
    Vtg,
    parse_nmea,
)
from protocol.unicore import Heading, parse_unicore

MAX_LINE_BYTES: Final = 1024  # longer than any log we decode; a longer "line" is noise
REJECTED_SNIPPET_CHARS: Final = 80  # how much of a rejected line we keep for diagnostics

GnssEvent = Rmc | Gga | Vtg | Hdt | Ths | Heading

# Reasons a line is rejected; stable strings, used as counter keys and in diagnostics.
REASON_CHECKSUM: Final = "checksum"
REASON_TRUNCATED: Final = "truncated"
REASON_MISSING_FIELD: Final = "missing_field"
REASON_BAD_FIELD: Final = "bad_field"
REASON_UNKNOWN: Final = "unknown_sentence"
REASON_MALFORMED: Final = "malformed"
REASON_GARBAGE: Final = "garbage"
REASON_OVERLONG: Final = "overlong"


@dataclass(frozen=True)
class Rejected:
    """A line that did not decode, with the counter key and the human-readable reason."""

    reason: str
    detail: str
    line: str  # the start of the offending line, for logs and the decode-gnss tool


def reason_of(exc: ProtocolError) -> str:
    """Map an exception to its counter key; most specific class first."""
    if isinstance(exc, ChecksumError):
        return REASON_CHECKSUM
    if isinstance(exc, TruncatedError):
        return REASON_TRUNCATED
    if isinstance(exc, UnknownSentenceError):
        return REASON_UNKNOWN
    if isinstance(exc, MissingFieldError):
        return REASON_MISSING_FIELD
    if isinstance(exc, FieldError):
        return REASON_BAD_FIELD
    if isinstance(exc, FrameError):
        return REASON_MALFORMED
    return REASON_MALFORMED


def decode_line(line: str) -> GnssEvent:
    """Decode one line (terminator optional); raise a ProtocolError subclass if it does not."""
    text = line.strip("\r\n ")
    if text.startswith("$"):
        return parse_nmea(text)
    if text.startswith("#"):
        return parse_unicore(text)
    if not text:
        raise TruncatedError("empty line")
    raise FrameError(f"garbage: line starts with {text[:1]!r}, not '$' or '#'")


def _snippet(raw: bytes) -> str:
    return raw[:REJECTED_SNIPPET_CHARS].decode("ascii", errors="backslashreplace")


class GnssLineDecoder:
    """Splits a byte stream on LF (CR stripped) and decodes each line.

    Resynchronisation: sentences never contain ``$`` or ``#`` inside, so a line is decoded from
    its *last* start character; anything before it (noise, the cut-off head of a sentence) is
    reported once as garbage, except complete sentences in it: when a line terminator was lost
    on the wire, the sentence before it still decodes. A line growing past ``MAX_LINE_BYTES``
    is dropped up to the next newline, so a receiver at the wrong baud rate cannot make us
    buffer without bound.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._discarding = False  # inside an overlong line: drop until the next newline
        self.counts: Counter[str] = Counter()  # "ok" and one key per rejection reason

    @property
    def buffered_bytes(self) -> int:
        """Bytes of an unfinished line held; never more than ``MAX_LINE_BYTES``."""
        return len(self._buf)

    @property
    def rejected_total(self) -> int:
        return sum(n for key, n in self.counts.items() if key != "ok")

    def feed(self, data: bytes) -> list[GnssEvent | Rejected]:
        """Consume bytes; return what the complete lines among them decoded to, in order."""
        out: list[GnssEvent | Rejected] = []
        start = 0
        while True:
            nl = data.find(b"\n", start)
            if nl < 0:
                self._append(data[start:], out)
                return out
            if self._discarding:
                self._discarding = False
            elif len(self._buf) + (nl - start) > MAX_LINE_BYTES:
                self._reject_overlong(out)
            else:
                self._buf += data[start:nl]
                self._line(bytes(self._buf), out)
            self._buf.clear()
            start = nl + 1

    def _append(self, chunk: bytes, out: list[GnssEvent | Rejected]) -> None:
        if self._discarding:
            return
        if len(self._buf) + len(chunk) > MAX_LINE_BYTES:
            self._reject_overlong(out)
            self._buf.clear()
            self._discarding = True
            return
        self._buf += chunk

    def _reject_overlong(self, out: list[GnssEvent | Rejected]) -> None:
        self._emit_reject(
            REASON_OVERLONG, f"line longer than {MAX_LINE_BYTES} bytes dropped", self._buf, out
        )

    def _emit_reject(
        self, reason: str, detail: str, raw: bytes | bytearray, out: list[GnssEvent | Rejected]
    ) -> None:
        self.counts[reason] += 1
        out.append(Rejected(reason, detail, _snippet(bytes(raw))))

    def _line(self, raw: bytes, out: list[GnssEvent | Rejected]) -> None:
        raw = raw.rstrip(b"\r")
        if not raw.strip():
            return  # blank lines carry nothing and are not an error
        cut = max(raw.rfind(b"$"), raw.rfind(b"#"))
        if cut < 0:
            self._emit_reject(REASON_GARBAGE, "no '$' or '#' start character", raw, out)
            return
        if cut > 0:
            self._prefix(raw[:cut], out)
            raw = raw[cut:]
        try:
            text = raw.decode("ascii")
        except UnicodeDecodeError:
            self._emit_reject(REASON_GARBAGE, "non-ASCII bytes in the line", raw, out)
            return
        try:
            event = decode_line(text)
        except ProtocolError as exc:
            self._emit_reject(reason_of(exc), str(exc), raw, out)
            return
        self.counts["ok"] += 1
        out.append(event)

    def _prefix(self, raw: bytes, out: list[GnssEvent | Rejected]) -> None:
        """What precedes a line's last sentence: whole sentences decode, the rest is garbage."""
        starts = [i for i, b in enumerate(raw) if b in b"$#"]
        bounds = list(zip(starts, [*starts[1:], len(raw)], strict=True)) if starts else []
        junk = len(raw) - sum(end - start for start, end in bounds)  # before the first start
        decoded: list[GnssEvent] = []
        for start, end in bounds:
            try:
                decoded.append(decode_line(raw[start:end].decode("ascii")))
            except (ProtocolError, UnicodeDecodeError):
                junk += end - start
        if junk:
            self._emit_reject(
                REASON_GARBAGE, f"{junk} bytes before the start character", raw, out
            )
        self.counts["ok"] += len(decoded)
        out.extend(decoded)

    def flush(self) -> list[GnssEvent | Rejected]:
        """End of stream (port closed): what is buffered is an unfinished line, say so."""
        out: list[GnssEvent | Rejected] = []
        if self._buf and not self._discarding:
            self._emit_reject(REASON_TRUNCATED, "stream ended inside a line", self._buf, out)
        self._buf.clear()
        self._discarding = False
        return out
