"""The seed-tube edge-capture module's UART protocol: one ASCII line per seed, ``D,<row>\\r\\n``.

The module watches every row's through-beam sensor and writes a line the moment a seed breaks
a beam. The line carries no timestamp, so the host must stamp it on arrival; the decoder is
therefore a pure byte → event function and the driver owns the clock.

Rules (rows are numbered 1..N from the left, as on the planter):

- a line ends with ``\\n``; a ``\\r`` before it is expected but not required, because some
  USB-UART adapters drop it and losing seeds over it would be worse than accepting it;
- ``D`` is the only record type; the row is a plain decimal without sign or leading zeros
  beyond a single digit run (``D,03`` is accepted as row 3 — firmware pads on some modules);
- anything else is a :class:`Rejected` with the precise reason, and decoding carries on with
  the next line: a glitch on the cable must cost one seed, never the stream.

The receive buffer is capped (:data:`MAX_LINE_BYTES`): a module stuck sending noise without
newlines cannot grow memory; the overlong run is rejected once and skipped up to the next
newline.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from protocol.errors import FieldError, FrameError, ProtocolError

MAX_LINE_BYTES = 32  # "D,128\r\n" is 7 bytes; generous room for padded firmware variants
MAX_ROWS = 128
RECORD_TYPE = "D"


@dataclass(frozen=True)
class SeedEdge:
    """One seed passed the sensor of ``row`` (1-based)."""

    row: int


# Kinds of rejected line: stable keys for the per-reason counters (the ``reason`` text varies).
KIND_OVERLONG = "overlong"  # more than MAX_LINE_BYTES without a newline
KIND_MALFORMED = "malformed"  # not 'D,<row>': empty, not ASCII, no comma, another record type
KIND_BAD_ROW = "bad_row"  # 'D,' with a row that is not a number or not on this planter


@dataclass(frozen=True)
class Rejected:
    """A line that is not a seed edge, with the reason a field engineer can act on and its
    stable counter key (``KIND_*``)."""

    line: bytes
    reason: str
    kind: str = field(default=KIND_MALFORMED, compare=False)


SeedLineEvent = SeedEdge | Rejected


def parse_seed_line(line: bytes, rows: int) -> SeedEdge:
    """Decode one line (terminator optional) or raise a ProtocolError subclass saying why."""
    body = line.rstrip(b"\n").removesuffix(b"\r")
    if not body:
        raise FrameError("empty line")
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError:
        raise FrameError("line is not ASCII") from None
    if not text.isprintable():
        raise FrameError("line contains control characters")
    kind, sep, row_text = text.partition(",")
    if not sep:
        raise FrameError(f"expected 'D,<row>', got no comma in {text!r}")
    if kind != RECORD_TYPE:
        raise FrameError(f"unknown record type {kind!r} (expected 'D')")
    if not row_text or not row_text.isdigit() or not row_text.isascii():
        raise FieldError(f"row must be a decimal number, got {row_text!r}")
    row = int(row_text)
    if not 1 <= row <= rows:
        raise FieldError(f"row {row} outside 1..{rows}")
    return SeedEdge(row)


def encode_seed_line(row: int) -> bytes:
    """The bytes the module sends for a seed in ``row`` (used by the simulator)."""
    if not 1 <= row <= MAX_ROWS:
        raise FieldError(f"row {row} outside 1..{MAX_ROWS}")
    return f"{RECORD_TYPE},{row}\r\n".encode("ascii")


class SeedLineDecoder:
    """Incremental decoder: feed whatever bytes the UART delivered, get events in order."""

    def __init__(self, rows: int) -> None:
        if not 1 <= rows <= MAX_ROWS:
            raise ValueError(f"rows must be 1..{MAX_ROWS}, got {rows}")
        self.rows = rows
        self._buf = bytearray()
        self._discarding = False  # inside an overlong line: skip up to the next newline
        self.edges = 0
        self.rejected = 0

    @property
    def buffered(self) -> int:
        """Bytes waiting for their newline (never above MAX_LINE_BYTES)."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[SeedLineEvent]:
        events: list[SeedLineEvent] = []
        start = 0
        while start < len(data):
            nl = data.find(b"\n", start)
            chunk = data[start:] if nl < 0 else data[start : nl + 1]
            start = len(data) if nl < 0 else nl + 1
            if self._discarding:
                if nl >= 0:
                    self._discarding = False
                continue
            self._buf += chunk
            if nl < 0:
                if len(self._buf) > MAX_LINE_BYTES:
                    events.append(
                        self._reject(
                            bytes(self._buf[:MAX_LINE_BYTES]), "line too long", KIND_OVERLONG
                        )
                    )
                    self._buf.clear()
                    self._discarding = True
                continue
            line = bytes(self._buf)
            self._buf.clear()
            if len(line) > MAX_LINE_BYTES:
                events.append(self._reject(line[:MAX_LINE_BYTES], "line too long", KIND_OVERLONG))
                continue
            try:
                events.append(parse_seed_line(line, self.rows))
                self.edges += 1
            except ProtocolError as exc:
                kind = KIND_BAD_ROW if isinstance(exc, FieldError) else KIND_MALFORMED
                events.append(self._reject(line, str(exc), kind))
        return events

    def _reject(self, line: bytes, reason: str, kind: str) -> Rejected:
        self.rejected += 1
        return Rejected(line, reason, kind)
