"""MQTT payload models: the documented schemas match the code, and the wire shapes are stable."""

from __future__ import annotations

import json
from datetime import UTC, datetime
from pathlib import Path

import pytest
from pydantic import ValidationError

from gateway.core.records import SeedRecord
from gateway.link.payloads import (
    SCHEMA_MODELS,
    CommandAck,
    EmptyCommand,
    RateCommand,
    SeedBatch,
    StatePayload,
    StatusPayload,
    main,
    render_schemas,
)

SCHEMA_DIR = Path(__file__).resolve().parents[3] / "docs" / "schemas"
T0 = datetime(2026, 4, 20, 8, 0, tzinfo=UTC)


def test_docs_schemas_are_up_to_date() -> None:
    """Fails when a payload model changed without `make schemas` (docs would lie)."""
    expected = render_schemas()
    on_disk = {p.name: p.read_text(encoding="utf-8") for p in SCHEMA_DIR.glob("*.json")}
    stale = sorted(n for n in expected if on_disk.get(n) != expected[n])
    extra = sorted(set(on_disk) - set(expected))
    assert not stale and not extra, (
        f"docs/schemas is stale (changed: {stale}, unexpected: {extra}); "
        "run `python -m gateway.link.payloads --write docs/schemas`"
    )


def test_schema_writer_cli_writes_every_model(tmp_path: Path) -> None:
    assert main(["--write", str(tmp_path)]) == 0
    assert sorted(p.stem for p in tmp_path.glob("*.json")) == sorted(SCHEMA_MODELS)
    schema = json.loads((tmp_path / "rate_command.json").read_text())
    assert set(schema["required"]) == {"crop", "rate_kg_ha"}


def test_ack_wire_shape_is_the_contract() -> None:
    assert json.loads(CommandAck(ok=True).to_json()) == {"ok": True}
    assert json.loads(CommandAck(ok=False, error="too fast").to_json()) == {
        "ok": False, "error": "too fast"
    }
    assert json.loads(CommandAck(ok=True, request_id="r1").to_json()) == {
        "ok": True, "request_id": "r1"
    }
    assert json.loads(CommandAck(ok=True, message="radar 48.7 m -> x1.0267").to_json()) == {
        "ok": True, "message": "radar 48.7 m -> x1.0267"
    }


def test_rate_command_accepts_the_documented_example() -> None:
    cmd = RateCommand.model_validate_json('{"crop": "wheat", "rate_kg_ha": 225.0}')
    assert (cmd.crop, cmd.rate_kg_ha) == ("wheat", 225.0)


@pytest.mark.parametrize(
    "payload",
    [
        {"crop": "wheat"},
        {"crop": "wheat", "rate_kg_ha": "lots"},
        {"crop": "wheat", "rate_kg_ha": -5},
        {"crop": "", "rate_kg_ha": 100},
        {"crop": "wheat", "rate_kg_ha": 100, "unexpected": 1},
        {"crop": 7, "rate_kg_ha": 100},
        # commands are strict: no lax coercion of strings or booleans into numbers
        {"crop": "wheat", "rate_kg_ha": "200"},
        {"crop": "wheat", "rate_kg_ha": True},
        {"crop": "wheat", "rate_kg_ha": 100, "request_id": 5},
    ],
)
def test_rate_command_rejects_bad_shapes(payload: dict[str, object]) -> None:
    with pytest.raises(ValidationError):
        RateCommand.model_validate(payload)


def test_rate_command_rejects_infinity() -> None:
    with pytest.raises(ValidationError, match="finite"):
        RateCommand.model_validate_json('{"crop": "wheat", "rate_kg_ha": Infinity}')


def test_empty_command_refuses_unknown_keys() -> None:
    assert EmptyCommand.model_validate({}).request_id is None
    with pytest.raises(ValidationError):
        EmptyCommand.model_validate({"force": True})


def test_only_work_state_crop_target_and_alarms_make_a_state_urgent() -> None:
    """Speed, tilt, duties and counters change on nearly every tick: they ride along at
    state_hz; the work state, crop, target rate and the set of alarms go out at once."""
    from gateway.link.payloads import ActiveAlarmInfo

    a = StatePayload(machine_id="m", utc=T0, work_state="seeding", speed_kmh=8.0, crop="wheat",
                     target_rate_kg_ha=200.0, motor_duty_pct=40.0, area_ha=1.0)
    alarm = ActiveAlarmInfo(code="rate.low_duty", severity="info", message="duty 3 %", since=T0)
    assert a.same_as(a.model_copy(update={"utc": datetime(2026, 4, 20, 9, tzinfo=UTC)}))
    assert a.same_as(a.model_copy(update={"speed_kmh": 9.0, "motor_duty_pct": 45.0,
                                          "area_ha": 1.1, "tilt_deg": 3.0}))
    assert not a.same_as(a.model_copy(update={"work_state": "turning"}))
    assert not a.same_as(a.model_copy(update={"crop": "maize"}))
    assert not a.same_as(a.model_copy(update={"target_rate_kg_ha": 210.0}))
    with_alarm = a.model_copy(update={"alarms": [alarm]})
    assert not a.same_as(with_alarm)
    live_text = alarm.model_copy(update={"message": "duty 2 %"})
    assert with_alarm.same_as(a.model_copy(update={"alarms": [live_text]}))
    assert not a.same_as(None)


def test_state_values_are_rounded_to_their_resolution() -> None:
    s = StatePayload(machine_id="m", utc=T0, work_state="seeding", speed_kmh=5.999999999999997,
                     tilt_deg=-2.00499, target_rate_kg_ha=224.99999999, commanded_rate_kg_ha=6.0001,
                     motor_duty_pct=41.04999, fan_duty_pct=60.00000001, area_ha=3.4200000007,
                     seed_mass_kg=769.5049)
    sent = json.loads(s.model_dump_json())
    assert (sent["speed_kmh"], sent["tilt_deg"]) == (6.0, -2.0)
    assert (sent["target_rate_kg_ha"], sent["commanded_rate_kg_ha"]) == (225.0, 6.0)
    assert (sent["motor_duty_pct"], sent["fan_duty_pct"]) == (41.0, 60.0)
    assert (sent["area_ha"], sent["seed_mass_kg"]) == (3.42, 769.505)
    assert StatePayload(machine_id="m", utc=T0, work_state="stopped").speed_kmh is None


def test_seed_batch_carries_record_ids() -> None:
    rec = SeedRecord(id=7, machine_id="m", row=1, utc=T0, lat=52.0, lon=13.0, fix="rtk_fixed",
                     speed_kmh=8.0)
    batch = json.loads(SeedBatch(machine_id="m", records=[rec]).model_dump_json())
    assert batch["records"][0]["id"] == 7


def test_status_is_a_bare_string_enum() -> None:
    assert StatusPayload("online").root == "online"
    with pytest.raises(ValidationError):
        StatusPayload("maybe")  # type: ignore[arg-type]


DOC = Path(__file__).resolve().parents[3] / "docs" / "mqtt.md"


def _doc_examples() -> list[dict[str, object]]:
    import re

    out = []
    for block in re.findall(r"```json\n(.*?)```", DOC.read_text(encoding="utf-8"), re.S):
        try:
            out.append(json.loads(block))
        except json.JSONDecodeError:  # one object per line (the ack examples)
            out.extend(json.loads(line) for line in block.splitlines() if line.strip())
    return out


def test_the_documented_examples_are_what_the_daemon_sends() -> None:
    """docs/mqtt.md is what dashboard authors code against: its state example used to say
    work_state "working" (no such state) and its alarm example a code nothing raises."""
    from gateway.control.work_state import WorkState
    from gateway.link.payloads import AlarmEvent

    state, batch, alarm = _doc_examples()[:3]
    s = StatePayload.model_validate(state)
    assert s.work_state in {w.value for w in WorkState}
    SeedBatch.model_validate(batch)
    a = AlarmEvent.model_validate(alarm)
    assert a.code in DOC.read_text(encoding="utf-8").split("## alarms")[1]


def test_state_schema_lists_exactly_the_work_states_and_speed_sources() -> None:
    from gateway.config import parse_config
    from gateway.control.controller import Controller
    from gateway.control.work_state import WorkState
    from gateway.core.alarms import AlarmBoard

    props = json.loads(render_schemas()["state.json"])["properties"]
    assert props["work_state"]["enum"] == [w.value for w in WorkState]
    # the controller's speed sources, plus "none" when no source is valid
    controller = Controller(parse_config({}), AlarmBoard("m"))
    assert props["speed_source"]["enum"] == [*controller.sources, "none"]
    table = DOC.read_text(encoding="utf-8").split("| `work_state` |")[1].split("\n\n")[0]
    assert all(f"| `{w.value}` |" in table for w in WorkState)


def test_a_new_rejection_count_alone_does_not_make_the_state_a_change() -> None:
    """A storm of garbage would otherwise publish the state at the 10 messages/s cap."""
    from gateway.link.payloads import RejectedInput

    a = StatePayload(machine_id="m", utc=T0, work_state="seeding", speed_kmh=8.0)
    b = a.model_copy(update={"rejected": RejectedInput(hmi={"garbage": 8239})})
    assert a.same_as(b)
    assert b.rejected.hmi == {"garbage": 8239}
