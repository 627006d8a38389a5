"""I/O for one device or bus each: reconnects, timeouts and typed readings live here."""
