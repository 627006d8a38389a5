"""The farm server: ``sowgate ingest`` takes every machine's records from the broker into
PostgreSQL, each exactly once, and tells each cab what is committed (docs/farm-server.md).

``db`` is all of the database I/O (schema, migration, COPY, the per-machine id coverage);
``ingest`` the MQTT side (shared subscription, validation, batching, the watermark);
``cli`` the ``sowgate ingest`` command (registered by entry point, like the dashboard).
"""
