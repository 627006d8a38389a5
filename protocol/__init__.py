"""Sans-I/O codecs: bytes or lines in, typed events out, and back.

Nothing in this package touches a clock, a socket, a serial port or asyncio, so every
codec can be fed captured bytes in a test exactly as it is fed live bytes in the field.
"""
