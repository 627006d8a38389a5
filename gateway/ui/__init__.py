"""What people look at in the cab.

- ``touchscreen``: the TJC touchscreen adapter (frames -> commands, state -> screen texts);
- ``terminal``: the rich terminal view of ``sowgate run --tui`` and the demo.
"""

__all__ = [
    "terminal",
    "touchscreen",
]
