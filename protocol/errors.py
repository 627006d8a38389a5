"""One exception root for the protocol layer, so callers can catch "the peer sent junk"
without also catching programming errors."""


class ProtocolError(ValueError):
    """Input that does not decode: bad checksum, bad framing, out-of-range field."""


class ChecksumError(ProtocolError):
    """The frame arrived whole but its checksum/CRC does not match."""


class FrameError(ProtocolError):
    """The bytes do not form a frame of the expected shape."""


class FieldError(ProtocolError):
    """A frame is well formed but a field value is invalid or out of range."""
