"""The set of active alarms, with raise/clear transitions reported once each.

Alarms are keyed by a stable code (``speed.lost``) so a dashboard can track one condition
across many raise/clear cycles, and so a condition re-evaluated every control tick does not
flood the operator, the record store and the ``alarms`` topic: re-raising an active alarm is
not a new event. Its message may carry a live value ("shaft speed 6.6 r/min outside ..."),
so a new message only updates the active alarm (what ``state.alarms`` and the screen show);
an event is emitted when the alarm is raised, when its severity changes, and when it clears.

A critical alarm must be acknowledged, as on commercial seeder terminals: once raised it stays
in ``unacknowledged`` (shown on the touchscreen's alarm line and in ``state.unacknowledged``)
until the operator acknowledges it (command ``ack_alarm``), even after it has cleared, so a
fault that came and went while nobody looked at the screen is still seen.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime

from gateway.core.alarm_codes import lookup
from gateway.core.errors import CommandError
from gateway.core.records import AlarmEvent, AlarmSeverity

log = logging.getLogger(__name__)


@dataclass
class ActiveAlarm:
    code: str
    message: str
    severity: AlarmSeverity
    since: datetime


class AlarmBoard:
    def __init__(
        self,
        machine_id: str = "",
        on_event: Callable[[AlarmEvent], None] | None = None,
        utcnow: Callable[[], datetime] = lambda: datetime.now(UTC),
    ) -> None:
        self._machine_id = machine_id
        self._active: dict[str, ActiveAlarm] = {}
        # critical alarms raised and not acknowledged yet, active or cleared since
        self._unacknowledged: dict[str, ActiveAlarm] = {}
        self._listeners: list[Callable[[AlarmEvent], None]] = []
        if on_event is not None:
            self._listeners.append(on_event)
        self._utcnow = utcnow

    def subscribe(self, listener: Callable[[AlarmEvent], None]) -> None:
        self._listeners.append(listener)

    def _emit(self, event: AlarmEvent) -> None:
        for listener in self._listeners:
            listener(event)

    def raise_(self, code: str, message: str, severity: AlarmSeverity = "warning") -> None:
        current = self._active.get(code)
        if current is None and lookup(code) is None:
            # gateway/core/alarm_codes.py is the documented list; tests check it is complete
            log.error("alarm code %r is not in gateway.core.alarm_codes.REGISTRY", code)
        if current is not None and current.severity == severity:
            current.message = message  # the live text, without an event per tick
            return
        now = self._utcnow()
        self._active[code] = ActiveAlarm(code, message, severity, current.since if current else now)
        if severity == "critical":
            self._unacknowledged[code] = ActiveAlarm(code, message, severity, now)
        self._emit(
            AlarmEvent(
                machine_id=self._machine_id,
                code=code,
                active=True,
                severity=severity,
                message=message,
                utc=now,
            )
        )

    def clear(self, code: str) -> None:
        current = self._active.pop(code, None)
        if current is None:
            return
        self._emit(
            AlarmEvent(
                machine_id=self._machine_id,
                code=code,
                active=False,
                severity=current.severity,
                message=current.message,
                utc=self._utcnow(),
            )
        )

    def set(
        self, code: str, active: bool, message: str, severity: AlarmSeverity = "warning"
    ) -> None:
        """Raise or clear in one call: convenient where a condition is re-evaluated each tick."""
        if active:
            self.raise_(code, message, severity)
        else:
            self.clear(code)

    def acknowledge(self, code: str | None = None) -> str:
        """The operator saw it: ``code`` (or, with None, every critical alarm waiting) leaves
        ``unacknowledged``. A still active alarm stays active (and listed in ``active``)."""
        if code is None:
            codes = list(self._unacknowledged)
            if not codes:
                return "no critical alarm to acknowledge"
        elif code not in self._unacknowledged:
            waiting = ", ".join(self._unacknowledged) or "none"
            raise CommandError(
                f"no critical alarm {code!r} to acknowledge (waiting: {waiting})"
            )
        else:
            codes = [code]
        for c in codes:
            del self._unacknowledged[c]
        log.info("alarm acknowledged: %s", ", ".join(codes))
        return f"acknowledged: {', '.join(codes)}"

    @property
    def unacknowledged(self) -> list[ActiveAlarm]:
        """Critical alarms raised and not acknowledged yet (active or cleared), oldest first."""
        return sorted(self._unacknowledged.values(), key=lambda a: a.since)

    def is_active(self, code: str) -> bool:
        return code in self._active

    @property
    def active(self) -> list[ActiveAlarm]:
        return sorted(self._active.values(), key=lambda a: a.since)
