"""``sowgate ingest --config FILE [--migrate]``: registered by entry point (``sowgate.commands``
in pyproject.toml) so the daemon never imports psycopg.

``--migrate`` creates or upgrades the schema and exits: run it as the database owner, since
the ingest user itself only reads and inserts (docs/farm-server.md, "Setup").
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
from pathlib import Path
from typing import Any

from gateway.config import EXIT_CONFIG, ConfigError, load_config

log = logging.getLogger("sowgate.ingest")

EXIT_SCHEMA = 65  # EX_DATAERR: the database holds a schema this ingest cannot write


def cmd_ingest(args: argparse.Namespace) -> int:
    try:
        settings = load_config(args.config)
    except ConfigError as exc:
        for line in exc.problems:
            print(line, file=sys.stderr)
        return EXIT_CONFIG
    farm = settings.farm_server
    url = args.database_url or farm.database_url
    if not url:
        print("farm_server.database_url: required by sowgate ingest (e.g. "
              "'postgresql://sowgate_ingest@127.0.0.1/farm')", file=sys.stderr)
        return EXIT_CONFIG
    farm.database_url = url
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr,
    )
    import psycopg

    from gateway.farm_server.db import SCHEMA_VERSION, SchemaError, ensure_schema, migrate
    from gateway.farm_server.ingest import Ingest

    try:
        if args.migrate:
            found = migrate(url)
            print(f"sowgate ingest: schema ready (was version {found})", file=sys.stderr)
            return 0
        found = ensure_schema(url)  # migrates itself when it may; refuses a newer schema
        if found != SCHEMA_VERSION:
            print(f"sowgate ingest: schema migrated from version {found} to {SCHEMA_VERSION}",
                  file=sys.stderr)
        ingest = Ingest(farm, settings.mqtt)
    except SchemaError as exc:
        print(f"sowgate ingest: {exc}", file=sys.stderr)
        return EXIT_SCHEMA
    except psycopg.OperationalError as exc:
        print(f"farm_server.database_url: cannot connect: {str(exc).strip()}", file=sys.stderr)
        return 69  # EX_UNAVAILABLE: systemd restarts it
    print(f"sowgate ingest: MQTT {settings.mqtt.host}:{settings.mqtt.port}, share group "
          f"{farm.share_group}, prefix {farm.topic_prefix}", file=sys.stderr, flush=True)
    try:
        asyncio.run(ingest.run())
    except KeyboardInterrupt:
        return 130
    return 0


def add_ingest_command(sub: Any) -> None:
    """``sowgate ingest``, registered by entry point (``sowgate.commands``)."""
    p = sub.add_parser("ingest", help="farm server: commit every machine's records from the "
                       "broker into PostgreSQL (docs/farm-server.md)")
    p.add_argument("--config", required=True, type=Path,
                   help="TOML config file ([farm_server], [mqtt])")
    p.add_argument("--database-url", default=None,
                   help="overrides farm_server.database_url (e.g. the owner's, with --migrate)")
    p.add_argument("--migrate", action="store_true",
                   help="create or upgrade the schema (as the database owner) and exit")
    p.set_defaults(func=cmd_ingest)
