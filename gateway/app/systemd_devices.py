"""The device nodes the config opens, as a systemd drop-in narrowing ``sowgate.service``.

The shipped unit allows the serial and GPIO device *classes* (``DeviceAllow=char-ttyS rw`` …)
so that it starts on any box; install.sh then writes what this module prints to
``/etc/systemd/system/sowgate.service.d/devices.conf``: an empty ``DeviceAllow=`` (which drops
the unit's classes) followed by one ``DeviceAllow=<path> rw`` per port the config names, so
the service can open its configured ports and no other serial port (the console on ttyS0, a
second board UART, another program's adapter): EPERM from the device cgroup.

systemd resolves each path (udev symlinks included) to its device number when the service
starts. A USB serial adapter (ttyUSB, ttyACM) gets a new number when it re-enumerates while
the old one is still held open (a loose plug in a vibrating cab), which a fixed number would
then refuse until the next start: when a configured port is such an adapter, or cannot be
resolved now (not plugged in, or udev not running: an image build), the drop-in keeps those
two USB classes allowed and says so. Board UARTs (ttyS, ttyAMA, ttymxc …) are never
re-numbered and are allowed one by one.
"""

from __future__ import annotations

import os
from pathlib import Path

from gateway.config import Settings

DROPIN = "/etc/systemd/system/sowgate.service.d/devices.conf"
HOTPLUG_CLASSES = ("char-ttyUSB", "char-ttyACM")
HOTPLUG_PREFIXES = ("ttyUSB", "ttyACM")


def configured_devices(settings: Settings) -> list[tuple[str, str]]:
    """(config key, device path) of every device node an enabled part opens."""
    out: list[tuple[str, str]] = []
    if settings.rs485.enabled:
        out.append(("rs485.port", settings.rs485.port))
    if settings.hmi.enabled:
        out.append(("hmi.port", settings.hmi.port))
    if settings.gnss.enabled:
        out.append(("gnss.port", settings.gnss.port))
    s = settings.seed_sensors
    if s.enabled:
        out.append(("seed_sensors.gpio_chip", s.gpio_chip) if s.source == "gpio"
                   else ("seed_sensors.port", s.port))
    return out


def hotplug(path: str) -> tuple[bool, str]:
    """(whether the port may be a re-enumerating USB adapter, what it is now)."""
    try:
        real = os.path.realpath(path, strict=True)
    except OSError:
        return True, "not present now"
    name = Path(real).name
    return name.startswith(HOTPLUG_PREFIXES), real


def device_allow_dropin(settings: Settings, config_path: str | os.PathLike[str]) -> str:
    """The drop-in's text: the unit's device classes replaced by the configured ports."""
    lines = [
        f"# written by install.sh from `sowgate check-config --systemd-device-allow "
        f"{config_path}`",
        "# (gateway/app/systemd_devices.py): the service may open these devices and no other.",
        "# Changed the ports in the config? Run that command again into this file, then",
        "#   systemctl daemon-reload && systemctl restart sowgate",
        "[Service]",
        "DeviceAllow=",
    ]
    usb: list[str] = []
    for key, path in configured_devices(settings):
        maybe_usb, now = hotplug(path)
        lines += [f"# {key}: {path} ({now})", f"DeviceAllow={path} rw"]
        if maybe_usb:
            usb.append(key)
    if usb:
        lines.append(f"# {', '.join(usb)}: a USB serial adapter (or not resolvable now); its "
                     "device number changes")
        lines.append("# when it re-enumerates while held open, so the USB serial classes stay "
                     "allowed:")
        lines += [f"DeviceAllow={cls} rw" for cls in HOTPLUG_CLASSES]
    return "\n".join(lines) + "\n"
