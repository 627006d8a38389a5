"""The periodic summary of rejected input: one INFO line a minute when anything was rejected."""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass, field

import pytest

from drivers.tasks import cancel_and_wait
from gateway.app.rejected_input import RejectedInputs
from tests.helpers import eventually


@dataclass
class _Stats:
    rejected: dict[str, int] = field(default_factory=dict)
    discarded_bytes: int = 0
    rejected_by_reason: dict[str, int] = field(default_factory=dict)


@dataclass
class _Device:
    stats: _Stats = field(default_factory=_Stats)


def test_the_summary_names_what_grew_since_the_last_one_and_is_none_when_nothing_did() -> None:
    gnss, hmi = _Device(), _Device()
    inputs = RejectedInputs(gnss=gnss, hmi=hmi)
    assert inputs.summary() is None
    gnss.stats.rejected.update(checksum=3, unknown_sentence=10)
    gnss.stats.discarded_bytes = 4096
    hmi.stats.rejected_by_reason["garbage"] = 8239
    assert inputs.summary() == (
        "gnss: checksum 3, unknown_sentence 10; hmi: garbage 8239; "
        "gnss bytes discarded (binary output?): 4096"
    )
    assert inputs.summary() is None
    gnss.stats.rejected["checksum"] = 5
    assert inputs.summary() == "gnss: checksum 2"
    assert inputs.counts().gnss == {"checksum": 5, "unknown_sentence": 10}


async def test_run_logs_the_summary_at_info(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="gateway.app.rejected_input")
    hmi = _Device()
    inputs = RejectedInputs(hmi=hmi, interval_s=0.01)
    hmi.stats.rejected_by_reason["unknown_function"] = 2
    task = asyncio.create_task(inputs.run())
    try:
        await eventually(lambda: caplog.records, 2.0, "the first summary", interval=0.01)
    finally:
        await cancel_and_wait(task)
    (record,) = caplog.records  # once: nothing new after the first summary
    assert record.levelno == logging.INFO
    assert "hmi: unknown_function 2" in record.getMessage()
