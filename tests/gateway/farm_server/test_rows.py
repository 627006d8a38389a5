"""``gateway.farm_server.rows``: the fast path from a ``seeds`` payload to binary COPY rows
accepts nothing pydantic's ``SeedBatch`` refuses, gives the values pydantic gives, and its
rows are what PostgreSQL reads back as the published values (real PostgreSQL)."""

from __future__ import annotations

import math
import random
from typing import Any

import orjson
import psycopg
import pytest
from pydantic import ValidationError

from gateway.core.records import SeedRow, seed_batch_json, utc_to_us
from gateway.farm_server.db import IngestDatabase
from gateway.farm_server.rows import RowEncoder, parse_seed_batch, rows_of_records
from gateway.link.payloads import SeedBatch
from tests.gateway.farm_server.conftest import rows

US0 = 1_776_729_598_000_000  # 2026-04-20T23:59:58Z: the batch crosses midnight


def stored(k: int, *, nulls: bool = False) -> SeedRow:
    """A stored seed as the cab keeps it (seed_batch_json's input), every field varied."""
    fixes = ("rtk_fixed", "rtk_float", "dgps", "single", "none")
    return (
        US0 + k * 5_123, 1 + k % 48, 48.0 + k * 1.1e-7, -15.0 - k * 1e-7, fixes[k % 5],
        8.0 + (k % 7) * 0.5, None if nulls and k % 3 == 0 else (k * 7.3) % 360.0,
        ("dual_antenna", "course", "none")[k % 3], bool(k % 4 == 0),
        ("interpolated", "paper", "oracle")[k % 3],
        None if nulls and k % 5 == 0 else 0.1 + (k % 11) * 0.01,
        ("dual_antenna", "inclinometer", "none")[k % 3],
        None if nulls and k % 2 == 0 else -3.5 + k % 9, None if nulls else 1.25 - k % 4,
        118.0, 0.0, 0.0,
    )


def payload(machine: str, n: int, *, nulls: bool = False, first: int = 1) -> bytes:
    return seed_batch_json(machine, list(range(first, first + n)),
                           [stored(k, nulls=nulls) for k in range(n)])


def pydantic_rows(machine: str, data: bytes) -> tuple[list[int], list[bytes]] | None:
    try:
        batch = SeedBatch.model_validate_json(data)
    except ValidationError:
        return None
    if batch.machine_id != machine or any(r.machine_id != machine for r in batch.records):
        return None
    try:
        got = rows_of_records(machine, batch.records)
    except ValueError:  # an id beyond a bigint: refused too
        return None
    return got.ids, got.rows


def fast_rows(machine: str, data: bytes) -> tuple[list[int], list[bytes]] | None:
    got = parse_seed_batch(data, machine, RowEncoder(machine))
    return None if got is None else (got.rows.ids, got.rows.rows)


@pytest.mark.parametrize("nulls", [False, True])
def test_the_cabs_own_batches_take_the_fast_path_with_pydantics_values(nulls: bool) -> None:
    data = payload("seeder-01", 500, nulls=nulls, first=7)
    fast = fast_rows("seeder-01", data)
    assert fast is not None
    assert fast == pydantic_rows("seeder-01", data)
    assert fast[0] == list(range(7, 507))
    got = parse_seed_batch(data, "seeder-01", RowEncoder("seeder-01"))
    assert got is not None and {d.isoformat() for d in got.rows.days} == {
        "2026-04-20", "2026-04-21"}


# (path into the document, value): each makes a payload pydantic may accept or refuse
MUTATIONS: list[tuple[tuple[Any, ...], Any]] = [
    (("records", 3, "row"), 0), (("records", 3, "row"), 129), (("records", 3, "row"), 128),
    (("records", 3, "row"), 5.0), (("records", 3, "row"), "5"), (("records", 3, "row"), True),
    (("records", 3, "id"), 0), (("records", 3, "id"), -1), (("records", 3, "id"), 2**63),
    (("records", 3, "lat"), 90.5), (("records", 3, "lat"), 90), (("records", 3, "lat"), -90.0),
    (("records", 3, "lon"), 180.0001), (("records", 3, "lon"), "15.0"),
    (("records", 3, "speed_kmh"), -0.1), (("records", 3, "speed_kmh"), 0.0),
    (("records", 3, "speed_kmh"), 1e308), (("records", 3, "heading_deg"), 360.0),
    (("records", 3, "heading_deg"), 359.999), (("records", 3, "heading_deg"), -0.0),
    (("records", 3, "heading_deg"), None), (("records", 3, "spacing_m"), -1e-9),
    (("records", 3, "roll_deg"), 90.0), (("records", 3, "roll_deg"), 90.01),
    (("records", 3, "pitch_deg"), -90.01), (("records", 3, "accuracy_m"), -0.5),
    (("records", 3, "accuracy_m"), None), (("records", 3, "accuracy_m"), 7),
    (("records", 3, "fix"), "rtk"), (("records", 3, "fix"), ["rtk_fixed"]),
    (("records", 3, "fix"), {"a": 1}), (("records", 3, "heading_source"), "gyro"),
    (("records", 3, "method"), "guess"), (("records", 3, "attitude"), None),
    (("records", 3, "extrapolated"), 1), (("records", 3, "extrapolated"), "true"),
    (("records", 3, "extrapolated"), None),
    (("records", 3, "utc"), "2026-04-20T23:59:58Z"),
    (("records", 3, "utc"), "2026-04-20T23:59:58.123Z"),
    (("records", 3, "utc"), "2026-04-20T23:59:58.123456+02:00"),
    (("records", 3, "utc"), "2026-02-30T23:59:58.123456Z"),
    (("records", 3, "utc"), "2026-04-20T24:00:00.000000Z"),
    (("records", 3, "utc"), "2026-04-20T23:59:60.000000Z"),
    (("records", 3, "utc"), "2026-04-20 23:59:58.123456Z"),
    (("records", 3, "utc"), "２026-04-20T23:59:58.123456Z"),
    (("records", 3, "utc"), "2026-04-20T23:59:58.12345６Z"),
    (("records", 3, "utc"), 1776729598), (("records", 3, "utc"), None),
    (("records", 3, "machine_id"), "seeder-02"), (("records", 3, "machine_id"), 1),
    (("records", 3, "delay_ms"), 12.0), (("records", 3, "colour"), "red"),
    (("records", 3), None), (("records", 3), []), (("records",), {}),
    (("records",), []), (("machine_id",), "seeder-02"), (("pending_from",), 0),
    (("pending_from",), 5), (("pending_from",), None), (("pending_from",), 2.0),
    (("extra",), 1),
]


def _mutated(doc: Any, path: tuple[Any, ...], value: Any) -> Any:
    doc = orjson.loads(orjson.dumps(doc))
    target = doc
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    return doc


@pytest.mark.parametrize(("path", "value"), MUTATIONS)
def test_the_fast_path_never_accepts_what_pydantic_refuses(path: tuple[Any, ...],
                                                           value: Any) -> None:
    doc = orjson.loads(payload("seeder-01", 10))
    data = orjson.dumps(_mutated(doc, path, value))
    fast, slow = fast_rows("seeder-01", data), pydantic_rows("seeder-01", data)
    if fast is not None:  # when it judges, it judges as pydantic does, to the byte
        assert fast == slow


def test_random_byte_damage_never_gets_past_both() -> None:
    rng = random.Random(24)
    good = payload("seeder-01", 20, nulls=True)
    judged = 0
    for _ in range(600):
        data = bytearray(good)
        for _ in range(rng.randint(1, 3)):
            data[rng.randrange(len(data))] = rng.choice(b'0123456789.-e",:{}[]ntfaZT ')
        fast = fast_rows("seeder-01", bytes(data))
        if fast is not None:
            judged += 1
            assert fast == pydantic_rows("seeder-01", bytes(data))
    assert judged > 10  # some damage stays valid and takes the fast path (else no test)


def test_the_rows_are_read_back_as_published(database: str) -> None:
    """What the fast path COPYs is what the cab published, value for value (floats to the
    last bit), and the point is the one PostGIS makes."""
    data = payload("seeder-01", 300, nulls=True)
    got = parse_seed_batch(data, "seeder-01", RowEncoder("seeder-01"))
    assert got is not None
    db = IngestDatabase(database)
    try:
        db.write_seed_rows({"seeder-01": got.rows})
    finally:
        db.close()
    want = SeedBatch.model_validate_json(data).records
    with psycopg.connect(database) as conn:
        back = conn.execute(
            "SELECT id, row, utc, lat, lon, fix, speed_kmh, heading_deg, heading_source, "
            "extrapolated, method, spacing_m, attitude, roll_deg, pitch_deg, "
            "ST_X(geom), ST_Y(geom), ST_SRID(geom) FROM seed_records ORDER BY id").fetchall()
    assert len(back) == len(want) == 300
    for r, b in zip(want, back, strict=True):
        assert b[:15] == (r.id, r.row, r.utc, r.lat, r.lon, r.fix, r.speed_kmh, r.heading_deg,
                          r.heading_source, r.extrapolated, r.method, r.spacing_m,
                          r.attitude, r.roll_deg, r.pitch_deg)
        assert utc_to_us(b[2]) == utc_to_us(r.utc)
        assert (b[15], b[16], b[17]) == (r.lon, r.lat, 4326)
        assert not any(isinstance(v, float) and math.isnan(v) for v in b)
    assert rows(database, "SELECT count(*) FROM seed_records WHERE NOT ST_Equals(geom, "
                "ST_SetSRID(ST_MakePoint(lon, lat), 4326))") == [(0,)]
