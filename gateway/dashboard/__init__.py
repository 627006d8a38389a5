"""``sowgate dashboard``: a web page with the live seed map, rates, per-row quality and alarms.

Its own process, an MQTT subscriber on the topics of docs/mqtt.md (so it works with any broker,
including Debian's mosquitto without a WebSocket listener, and with several seeders on one
broker). It serves one page from package files (no CDN: the cab box often has no internet)
and pushes updates to it over a WebSocket.

- ``model``: what is known about each machine, built from MQTT payloads (pure, no I/O);
- ``subscriber``: the MQTT session (reconnects for ever) feeding the model, sending commands;
- ``server``: the Starlette app (page, WebSocket, commands, password);
- ``cli``: the ``sowgate dashboard`` subcommand (registered by entry point).

Nothing in gateway/ imports this package but the app layer.
"""
