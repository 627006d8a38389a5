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
    on the wire, the sentence before it still decodes.

    A line growing past ``MAX_LINE_BYTES`` is what a receiver that mixes binary logs and NMEA
    on one port produces (u-blox UBX, Unicore binary logs: kilobytes without a newline, then
    ``$GNRMC...``). Its head is dropped, not the whole line: the decoder keeps the longest tail
    that begins with a start character and fits in ``MAX_LINE_BYTES`` (with none, it drops
    everything up to the next start character or newline). So the buffer stays capped, the
    sentence after the binary still decodes, the line is counted once as ``overlong`` and the
    dropped bytes are counted exactly in ``discarded_bytes``. What is kept depends only on the
    bytes, never on how the reads split them.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._skipping = False  # head of an overlong line: drop up to the next '$', '#' or LF
        self._overlong = False  # the current line has already been reported as overlong
        self.counts: Counter[str] = Counter()  # "ok" and one key per rejection reason
        self.discarded_bytes = 0  # dropped from overlong lines without being decoded

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
            self._append(data[start:nl], out)
            if not self._skipping:
                self._line(bytes(self._buf), out)
            self._end_line()
            start = nl + 1

    def _end_line(self) -> None:
        self._buf.clear()
        self._skipping = False
        self._overlong = False

    def _append(self, chunk: bytes, out: list[GnssEvent | Rejected]) -> None:
        """Add part of a line (no LF in it), cutting the head of a line that grows too long."""
        if self._skipping:
            cut = _first_start(chunk, 0)
            if cut < 0:
                self.discarded_bytes += len(chunk)
                return
            self.discarded_bytes += cut
            chunk = chunk[cut:]
            self._skipping = False
        if len(self._buf) + len(chunk) <= MAX_LINE_BYTES:
            self._buf += chunk
            return
        combined = self._buf + chunk
        if not self._overlong:
            self._overlong = True
            self._emit_reject(
                REASON_OVERLONG,
                f"more than {MAX_LINE_BYTES} bytes without a line end (binary output?): "
                "the bytes before the last sentence start are dropped",
                combined,
                out,
            )
        keep = _first_start(combined, len(combined) - MAX_LINE_BYTES)
        if keep < 0:  # no start character in the last MAX_LINE_BYTES: nothing worth keeping
            self.discarded_bytes += len(combined)
            self._buf.clear()
            self._skipping = True
        else:
            self.discarded_bytes += keep
            self._buf[:] = combined[keep:]

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
        if self._buf and not self._skipping:
            self._emit_reject(REASON_TRUNCATED, "stream ended inside a line", self._buf, out)
        self._end_line()
        return out


def _first_start(data: bytes | bytearray, offset: int) -> int:
    """Index of the first ``$`` or ``#`` at or after ``offset``, -1 if there is none."""
    dollar, hash_ = data.find(b"$", offset), data.find(b"#", offset)
    if dollar < 0 or hash_ < 0:
        return max(dollar, hash_)
    return min(dollar, hash_)
