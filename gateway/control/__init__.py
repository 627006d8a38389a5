"""Paper A's speed-following rate control, as plain state and arithmetic.

- ``speed``: the speed filters (paper A's mean, the trend filter);
- ``attitude``: raised/lowered from the inclinometer with hysteresis;
- ``work_state``: the work-state tables (operator mode x event -> mode; operator mode x
  speed x attitude -> fan, motor);
- ``rate_model``: kg/ha -> g/min -> shaft speed -> duty (paper A eq. 4-6) and back;
- ``controller``: one tick: readings in, duties and alarms out.

No I/O here: the RS485 loop that feeds it lives in ``gateway.app.daemon``.
"""

__all__ = [
    "attitude",
    "controller",
    "rate_model",
    "speed",
    "work_state",
]
