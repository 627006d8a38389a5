"""One exception root for the driver layer."""


class DriverError(Exception):
    """A device or bus could not be used (port missing, timeout, exception response)."""


class DeviceUnavailable(DriverError):
    """The device did not answer in time or the port has vanished."""


class DeviceRejected(DriverError):
    """The device answered with an error (e.g. a Modbus exception response)."""
