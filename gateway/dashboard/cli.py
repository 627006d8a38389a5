"""``sowgate dashboard --config FILE [--listen HOST:PORT]``: registered by entry point
(``sowgate.commands`` in pyproject.toml), so the daemon's CLI never imports the web stack."""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
from pathlib import Path
from typing import Any

from gateway.config import EXIT_CONFIG, ConfigError, dashboard_problems, load_config

log = logging.getLogger("sowgate.dashboard")


def _read_password(path: str) -> str:
    return Path(path).read_text(encoding="utf-8").strip()


def cmd_dashboard(args: argparse.Namespace) -> int:
    try:
        settings = load_config(args.config)
        if args.listen is not None:
            settings.dashboard.listen = args.listen
    except ConfigError as exc:
        for line in exc.problems:
            print(line, file=sys.stderr)
        return EXIT_CONFIG
    except ValueError as exc:  # --listen given in a form [dashboard] listen refuses
        print(f"--listen: must be HOST:PORT (got {args.listen!r}): {exc}", file=sys.stderr)
        return EXIT_CONFIG
    problems = dashboard_problems(settings)
    if problems:
        for line in problems:
            print(line, file=sys.stderr)
        return EXIT_CONFIG
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr,
    )
    from gateway.core.journal_logging import use_journal_priorities

    use_journal_priorities()
    import uvicorn

    from gateway.dashboard.server import create_app

    d = settings.dashboard
    password = _read_password(d.password_file) if d.password_file else None
    app = create_app(settings, password=password, database_url=args.database)
    if not settings.mqtt.enabled:
        log.warning("[mqtt] is off in %s: the dashboard connects to %s:%s all the same",
                    args.config, settings.mqtt.host, settings.mqtt.port)
    config = uvicorn.Config(
        app, host=d.host, port=d.port, ws="websockets-sansio", lifespan="on",
        log_level="debug" if args.verbose else "warning", access_log=False,
        # no proxy in front: X-Forwarded-For must not choose the client address the password
        # throttle counts failures by (gateway/dashboard/guard.py)
        proxy_headers=False,
    )
    server = uvicorn.Server(config)
    shown = f"[{d.host}]" if ":" in d.host else d.host
    farm = " + farm database" if (args.database or settings.farm_server.database_url) else ""
    print(f"sowgate dashboard: http://{shown}:{d.port}/ (MQTT {settings.mqtt.host}:"
          f"{settings.mqtt.port}{farm}; Ctrl-C to stop)", file=sys.stderr, flush=True)
    try:
        asyncio.run(server.serve())
    except KeyboardInterrupt:
        return 130
    return 0 if server.started else 1


def add_dashboard_command(sub: Any) -> None:
    """``sowgate dashboard``, registered by entry point (``sowgate.commands``)."""
    d = sub.add_parser("dashboard", help="serve the live web dashboard (an MQTT subscriber)")
    d.add_argument("--config", required=True, type=Path, help="TOML config file ([mqtt], "
                   "[commands], [dashboard])")
    d.add_argument("--listen", default=None, metavar="HOST:PORT",
                   help="address to serve on (default: [dashboard] listen, 127.0.0.1:8080)")
    d.add_argument("--database", default=None, metavar="URL",
                   help="the farm server's PostgreSQL (default: [farm_server] database_url): "
                   "adds the fleet view of any day (docs/farm-server.md)")
    d.set_defaults(func=cmd_dashboard)
