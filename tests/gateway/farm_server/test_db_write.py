"""``IngestDatabase.write_seed_batches``: one transaction for every machine of a flush, binary
COPY straight into ``seed_records``; the unique key stays the backstop (real PostgreSQL)."""

from __future__ import annotations

import psycopg

from gateway.farm_server.db import IngestDatabase
from tests.gateway.farm_server.conftest import rows
from tests.gateway.farm_server.test_ingest import records


def test_one_flush_of_several_machines_is_one_commit_with_their_coverage(database: str) -> None:
    db = IngestDatabase(database)
    try:
        done = db.write_seed_batches({
            "seeder-02": records("seeder-02", 1, 300),
            "seeder-01": records("seeder-01", 1, 200) + records("seeder-01", 150, 250),
        })
        assert [(c.machine_id, c.coverage, c.new_seeds, c.duplicate_seeds) for c in done] == [
            ("seeder-01", [(1, 250)], 250, 51), ("seeder-02", [(1, 300)], 300, 0)]
        # a replay and new ids of one machine: only the new ones are written
        again = db.write_seed_batches({"seeder-01": records("seeder-01", 240, 260)})
        assert (again[0].coverage, again[0].new_seeds, again[0].duplicate_seeds) == (
            [(1, 260)], 10, 11)
    finally:
        db.close()
    assert rows(database, "SELECT machine_id, count(*), count(DISTINCT id), min(id), max(id) "
                "FROM seed_records GROUP BY machine_id ORDER BY machine_id") == [
        ("seeder-01", 260, 260, 1, 260), ("seeder-02", 300, 300, 1, 300)]
    assert rows(database, "SELECT machine_id, lo, hi FROM seed_coverage ORDER BY machine_id") \
        == [("seeder-01", 1, 260), ("seeder-02", 1, 300)]
    # the point sent as EWKB is the one PostGIS makes from lon and lat
    assert rows(database, "SELECT count(*) FROM seed_records WHERE NOT ST_Equals(geom, "
                "ST_SetSRID(ST_MakePoint(lon, lat), 4326)) OR ST_SRID(geom) <> 4326") == [(0,)]


def test_a_row_the_coverage_does_not_list_is_not_stored_twice(database: str) -> None:
    """The COPY fails on the unique key; the flush is done again with ON CONFLICT DO NOTHING."""
    with psycopg.connect(database) as conn:
        r = records("seeder-01", 5, 5)[0]
        conn.execute("SELECT sowgate_ensure_day(%s)", (r.utc.date(),))
        conn.execute(
            "INSERT INTO seed_records (machine_id, id, row, utc, lat, lon, fix, speed_kmh, "
            "heading_source, extrapolated, method, attitude, geom) VALUES (%s, %s, %s, %s, "
            "%s, %s, %s, %s, 'none', false, 'interpolated', 'none', "
            "ST_SetSRID(ST_MakePoint(%s, %s), 4326))",
            (r.machine_id, r.id, r.row, r.utc, r.lat, r.lon, r.fix, r.speed_kmh, r.lon, r.lat))
    db = IngestDatabase(database)
    try:
        done = db.write_seed_batches({"seeder-01": records("seeder-01", 1, 10),
                                      "seeder-02": records("seeder-02", 1, 3)})
    finally:
        db.close()
    assert [(c.machine_id, c.coverage) for c in done] == [
        ("seeder-01", [(1, 10)]), ("seeder-02", [(1, 3)])]
    assert rows(database, "SELECT machine_id, count(*), count(DISTINCT id) FROM seed_records "
                "GROUP BY machine_id ORDER BY machine_id") == [
        ("seeder-01", 10, 10), ("seeder-02", 3, 3)]
