"""One exception root for the gateway layer."""


class GatewayError(Exception):
    """Base for errors the daemon reports to the operator."""


class ConfigError(GatewayError):
    """The configuration is invalid; ``problems`` holds one ``section.key: problem`` per line."""

    def __init__(self, problems: list[str]) -> None:
        super().__init__("\n".join(problems))
        self.problems = problems


class RateError(GatewayError):
    """A target rate cannot be met by the metering drive (too fast, outside calibration)."""


class TooFastError(RateError):
    """The target rate needs more than 100 % duty at the current speed."""

    def __init__(self, max_speed_kmh: float) -> None:
        super().__init__(f"too fast for target rate, max {max_speed_kmh:.1f} km/h")
        self.max_speed_kmh = max_speed_kmh


class OutsideCalibrationError(RateError):
    """The required shaft speed lies outside the range the metering model was fitted on."""


class CommandError(GatewayError):
    """An operator command (HMI or MQTT) was rejected; the message is shown to the operator."""
