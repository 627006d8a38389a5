"""The one TOML config file, validated by pydantic, with ``SOWGATE_<SECTION>__<KEY>`` overrides.

Every problem is reported as ``section.key: problem (got value)`` so a fitter reading a
terminal in a cab knows exactly which line of which table to fix.
"""

from __future__ import annotations

import difflib
import os
import re
import tomllib
import types
import typing
from pathlib import Path
from typing import Any

from pydantic import BaseModel, Field, ValidationError, model_validator
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict

from gateway.config._base import FieldProblem, OptionalPart, switch_on_present_parts
from gateway.config.agopengps import AgOpenGpsSection
from gateway.config.farm import (
    CommandsSection,
    DashboardSection,
    FarmServerSection,
    MqttSection,
    TlsSection,
)
from gateway.config.farm_task import FarmSection
from gateway.config.machine import (
    ActuatorsSection,
    CalibrationSection,
    ControlSection,
    CropModel,
    HmiSection,
    HopperScaleSection,
    InclinometerSection,
    MachineSection,
    RadarSection,
    Rs485Section,
    SpeedSection,
)
from gateway.config.metering import (
    CanSection,
    ChannelSection,
    IsobusSection,
    PrescriptionSection,
)
from gateway.config.recording import (
    GnssSection,
    HitchSection,
    PositioningSection,
    RowMonitorSection,
    SeedSensorsSection,
    StoreSection,
    row_lateral_from_width,
)
from gateway.config.startup import (
    dashboard_problems,
    input_file_problems,
    lock_state_dir,
    output_location_problems,
    parts_summary,
    prepare_state_dir,
    resolve_state_dir,
    start_problems,
    undriven_channels,
)
from gateway.core.errors import ConfigError
from gateway.core.files import UnreadableFile, read_regular_file

CONFIG_MAX_BYTES = 1_000_000  # a config is a few kB; a cap keeps /dev/zero from filling memory
EXIT_CONFIG = 78  # EX_CONFIG from sysexits.h; systemd's RestartPreventExitStatus uses it

__all__ = [
    "AS_APPLIED_FILE",
    "EXIT_CONFIG",
    "STORE_FILE",
    "ActuatorsSection",
    "AgOpenGpsSection",
    "CalibrationSection",
    "CanSection",
    "ChannelSection",
    "CommandsSection",
    "ConfigError",
    "ControlSection",
    "CropModel",
    "DashboardSection",
    "FarmSection",
    "FarmServerSection",
    "GnssSection",
    "HitchSection",
    "HmiSection",
    "HopperScaleSection",
    "InclinometerSection",
    "IsobusSection",
    "MachineSection",
    "MqttSection",
    "OptionalPart",
    "PositioningSection",
    "PrescriptionSection",
    "RadarSection",
    "RowMonitorSection",
    "Rs485Section",
    "SeedSensorsSection",
    "Settings",
    "SpeedSection",
    "StoreSection",
    "TlsSection",
    "as_applied_path",
    "dashboard_problems",
    "format_validation_error",
    "input_file_problems",
    "load_config",
    "lock_state_dir",
    "optional_parts",
    "output_location_problems",
    "parse_config",
    "parts_summary",
    "prepare_state_dir",
    "start_problems",
    "state_dir",
    "store_path",
    "undriven_channels",
]


class Settings(BaseSettings):
    """The whole daemon configuration. Tables absent from the file take their defaults."""

    model_config = SettingsConfigDict(
        env_prefix="SOWGATE_",
        env_nested_delimiter="__",
        extra="forbid",
        validate_assignment=True,
    )

    machine: MachineSection = Field(default_factory=MachineSection)
    rs485: Rs485Section = Field(default_factory=Rs485Section)
    radar: RadarSection = Field(default_factory=RadarSection)
    inclinometer: InclinometerSection = Field(default_factory=InclinometerSection)
    actuators: ActuatorsSection = Field(default_factory=ActuatorsSection)
    hmi: HmiSection = Field(default_factory=HmiSection)
    speed: SpeedSection = Field(default_factory=SpeedSection)
    control: ControlSection = Field(default_factory=ControlSection)
    calibration: CalibrationSection = Field(default_factory=CalibrationSection)
    gnss: GnssSection = Field(default_factory=GnssSection)
    seed_sensors: SeedSensorsSection = Field(default_factory=SeedSensorsSection)
    positioning: PositioningSection = Field(default_factory=PositioningSection)
    row_monitor: RowMonitorSection = Field(default_factory=RowMonitorSection)
    store: StoreSection = Field(default_factory=StoreSection)
    mqtt: MqttSection = Field(default_factory=MqttSection)
    commands: CommandsSection = Field(default_factory=CommandsSection)
    dashboard: DashboardSection = Field(default_factory=DashboardSection)
    can: CanSection = Field(default_factory=CanSection)
    channel: list[ChannelSection] = Field(default_factory=list)
    isobus: IsobusSection = Field(default_factory=IsobusSection)
    prescription: PrescriptionSection = Field(default_factory=PrescriptionSection)
    hopper_scale: HopperScaleSection = Field(default_factory=HopperScaleSection)
    farm: FarmSection = Field(default_factory=FarmSection)  # names for ISO-XML export
    agopengps: AgOpenGpsSection = Field(default_factory=AgOpenGpsSection)
    # `sowgate ingest` (the farm server) reads this table; the daemon does not
    farm_server: FarmServerSection = Field(default_factory=FarmServerSection)

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        # Environment beats the file: a service override can fix one value without editing it.
        return (env_settings, init_settings)

    @model_validator(mode="before")
    @classmethod
    def _present_parts_are_on(cls, data: Any) -> Any:
        """A table for an optional part says the machine has that part (``OptionalPart``).

        A fitter who writes ``[mqtt]`` with host and port, or ``[gnss]`` with its port, expects
        the part to run, not a daemon that silently ignores it because an ``enabled`` key was
        left out. ``enabled = false`` still switches one off; a file without the table keeps
        the part at its default. Environment overrides are merged in before this runs, so
        ``SOWGATE_MQTT__HOST`` creates the table as the file would.
        """
        if not isinstance(data, dict):
            return data
        return switch_on_present_parts(data, optional_parts())

    def deprecation_notes(self) -> list[str]:
        """Keys the file sets that do nothing any more, each with the key that does.

        They are accepted so an old config still loads; the daemon logs these at start and
        ``check-config`` prints them, because a fitter who set one believes it works.
        """
        notes: list[str] = []
        if "loop_hz" in self.control.ignored_keys:
            notes.append(
                f"control.loop_hz = {self.control.ignored_keys['loop_hz']} is deprecated and "
                "ignored: the control loop ticks once per RS485 poll, so set rs485.poll_hz "
                f"(now {self.rs485.poll_hz:g} Hz) instead and remove control.loop_hz"
            )
        return notes

    @model_validator(mode="after")
    def _cross_section(self) -> Settings:
        if self.seed_sensors.enabled and not self.gnss.enabled:
            raise ValueError(
                "seed_sensors is enabled but gnss is not: seed positions need the GNSS "
                "receiver (enable [gnss], or set seed_sensors.enabled = false)"
            )
        if "gnss" in self.speed.source and not self.gnss.enabled:
            raise ValueError(
                f"speed.source = {'_then_'.join(self.speed.source)!r} uses the GNSS speed but "
                "gnss is not enabled (add a [gnss] table, or choose another source)"
            )
        _check_agopengps(self)
        rows = self.machine.rows
        lateral = self.positioning.row_lateral_m
        if lateral is None:
            # omitted: follow the machine, so changing rows or width cannot leave stale offsets
            self.positioning.row_lateral_m = row_lateral_from_width(
                self.machine.working_width_m, rows
            )
        elif len(lateral) != rows:
            raise FieldProblem(
                "positioning.row_lateral_m",
                f"needs one entry per row, machine.rows is {rows} but it has {len(lateral)}",
                lateral,
            )
        lines = self.seed_sensors.gpio_lines
        if self.seed_sensors.source == "gpio" and self.seed_sensors.enabled and len(lines) != rows:
            raise FieldProblem(
                "seed_sensors.gpio_lines", f"needs one line per row ({rows})", lines
            )
        names = [c.name for c in self.channel]
        for i, name in enumerate(names):
            if name in names[:i]:
                raise FieldProblem(f"channel[{i}].name", "channel names must be unique", name)
        bus = {
            "radar": self.radar.device_id,
            "inclinometer": self.inclinometer.device_id,
            "actuators": self.actuators.device_id,
        }
        if self.hopper_scale.enabled:
            bus["hopper_scale"] = self.hopper_scale.device_id
        seen: dict[int, str] = {}
        for section, device_id in bus.items():
            if device_id in seen:
                raise FieldProblem(
                    f"{section}.device_id",
                    f"same as {seen[device_id]}.device_id; radar, inclinometer, actuators "
                    "(and hopper_scale) share one RS485 bus and each needs its own id",
                    device_id,
                )
            seen[device_id] = section
        pwm = [(i, c) for i, c in enumerate(self.channel) if c.drive == "pwm_modbus"]
        if len(pwm) > 1:
            raise ValueError(
                "only one channel may have drive = 'pwm_modbus': the RS485 PWM module drives "
                f"one metering motor (got {', '.join(c.name for _, c in pwm)})"
            )
        for i, ch in pwm:
            crops = self.control.crops
            if ch.product not in crops:
                raise ValueError(
                    f"channel[{i}].product = {ch.product!r}: a pwm_modbus channel meters one of "
                    f"the crops in control.crops ({', '.join(sorted(crops))}), whose fitted "
                    "motor and metering models it uses"
                )
            m = crops[ch.product]
            if not m.rate_min_kg_ha <= ch.target_rate_kg_ha <= m.rate_max_kg_ha:
                raise ValueError(
                    f"channel[{i}].target_rate_kg_ha = {ch.target_rate_kg_ha:g} is outside the "
                    f"{ch.product} range {m.rate_min_kg_ha:g}..{m.rate_max_kg_ha:g} kg/ha"
                )
        if not self.rs485.enabled:
            uses = []
            if "radar" in self.speed.source:
                uses.append("speed.source includes radar")
            if "inclinometer" in self.isobus.work_state_source:
                uses.append("isobus.work_state_source includes inclinometer")
            if self.hopper_scale.enabled:
                uses.append("hopper_scale is enabled")
            if self.positioning.attitude_source == "inclinometer":
                uses.append("positioning.attitude_source is inclinometer")
            uses += [f"channel {c.name} is pwm_modbus" for c in self.channel
                     if c.drive == "pwm_modbus"]
            if uses:
                raise ValueError(
                    f"rs485.enabled = false, but {'; '.join(uses)}: those devices are on the "
                    "RS485 bus (use gnss/isobus speed, the hitch work state, can_pid channels)"
                )
        # the one check of CAN node ids: the metering component and the CAN link trust it
        nodes: dict[int, int] = {}
        for i, ch in enumerate(self.channel):
            if ch.drive != "can_pid":
                continue
            if ch.node_id in nodes:
                first = nodes[ch.node_id]
                raise FieldProblem(
                    f"channel[{i}].node_id",
                    f"same as channel[{first}].node_id ({self.channel[first].name}); two "
                    "can_pid channels cannot share a node_id: each metering controller on the "
                    "CAN bus needs its own (1..15)",
                    ch.node_id,
                )
            nodes[ch.node_id] = i
        return self


def _check_agopengps(settings: Settings) -> None:
    """AgOpenGPS named as a speed or work-state source needs ``[agopengps]``; its section map
    names channels and rows that exist."""
    aog = settings.agopengps
    if not aog.enabled:
        if "agopengps" in settings.speed.source:
            raise FieldProblem("speed.source", "uses agopengps but [agopengps] is not enabled",
                               "_then_".join(settings.speed.source))
        if "agopengps" in settings.isobus.work_state_source:
            raise FieldProblem(
                "isobus.work_state_source", "uses agopengps but [agopengps] is not enabled",
                "_then_".join(settings.isobus.work_state_source),
            )
        return
    names = {c.name for c in settings.channel}
    for name in aog.channel_sides:
        if name not in names:
            raise FieldProblem(
                f"agopengps.channel_sides.{name}",
                f"no such channel (channels: {', '.join(sorted(names)) or 'none'})", name,
            )
    for i, sec in enumerate(aog.sections):
        if sec.channel is not None and sec.channel not in names:
            raise FieldProblem(
                f"agopengps.sections[{i}].channel",
                f"no such channel (channels: {', '.join(sorted(names)) or 'none'})", sec.channel,
            )
        bad = [r for r in sec.rows if r > settings.machine.rows]
        if bad:
            raise FieldProblem(
                f"agopengps.sections[{i}].rows",
                f"rows are 1..{settings.machine.rows} (machine.rows)", bad,
            )


def optional_parts() -> list[str]:
    """The tables of ``Settings`` that are optional parts, in the order they are declared."""
    parts = []
    for name, field in Settings.model_fields.items():
        kind = field.annotation
        if isinstance(kind, type) and issubclass(kind, OptionalPart):
            parts.append(name)
    return parts


def _loc(loc: tuple[int | str, ...]) -> str:
    out = ""
    for item in loc:
        out += f"[{item}]" if isinstance(item, int) else ("." if out else "") + str(item)
    return out


def _env_variable(loc: tuple[int | str, ...]) -> str | None:
    """The ``SOWGATE_…`` variable that set the value at ``loc`` (or a table holding it), if any.

    The environment beats the file, so when such a variable exists the bad value is its value,
    and a fitter who looks in the file would find nothing wrong there.
    """
    if not loc or not all(isinstance(part, str) for part in loc):
        return None  # list items ([[channel]]) cannot be set one by one from the environment
    by_upper = {name.upper(): name for name in os.environ}
    prefix = Settings.model_config.get("env_prefix", "")
    delimiter = Settings.model_config.get("env_nested_delimiter") or "__"
    for n in range(len(loc), 0, -1):
        name = by_upper.get((prefix + delimiter.join(str(p) for p in loc[:n])).upper())
        if name is not None:
            return name
    return None


def _without_none(kind: Any) -> Any:
    args = [a for a in typing.get_args(kind) if a is not type(None)]
    if typing.get_origin(kind) in (typing.Union, types.UnionType) and len(args) == 1:
        return args[0]
    return kind


def _model_at(loc: tuple[int | str, ...]) -> type[BaseModel] | None:
    """The config model (table) that the path ``loc`` leads to, for naming its valid keys."""
    kind: Any = Settings
    for part in loc:
        kind = _without_none(kind)
        if typing.get_origin(kind) in (list, dict):
            kind = typing.get_args(kind)[-1]  # part is a [[table]] index or a dict key
            continue
        if not (isinstance(kind, type) and issubclass(kind, BaseModel)):
            return None
        fields = {f.alias or name: f for name, f in kind.model_fields.items()}
        if part not in fields:
            return None
        kind = fields[str(part)].annotation
    kind = _without_none(kind)
    return kind if isinstance(kind, type) and issubclass(kind, BaseModel) else None


def _closest_key(loc: tuple[int | str, ...]) -> str | None:
    """For an unknown key, the valid key of the same table it most likely misspells."""
    model = _model_at(loc[:-1])
    if model is None or not isinstance(loc[-1], str):
        return None
    keys = [f.alias or name for name, f in model.model_fields.items()]
    match = difflib.get_close_matches(loc[-1], keys, n=1, cutoff=0.6)
    return match[0] if match else None


def format_validation_error(exc: ValidationError) -> list[str]:
    """One ``section.key: problem (got value)`` line per pydantic error.

    A value set by an environment variable says so (``rs485.poll_hz (from
    $SOWGATE_RS485__POLL_HZ): …``), and an unknown key suggests the valid one it most likely
    misspells (``did you mean baudrate?``).
    """
    lines = []
    for err in exc.errors(include_url=False):
        raw_loc = tuple(err["loc"])
        loc = _loc(raw_loc)
        msg = err["msg"].removeprefix("Value error, ")
        got = err.get("input")
        problem = err.get("ctx", {}).get("error")
        if isinstance(problem, FieldProblem):
            key = problem.key if problem.key.startswith("[") else "." + problem.key
            loc = problem.key if not loc else loc + key
            msg, got = problem.problem, problem.value
            raw_loc = tuple(
                int(p) if p.isdigit() else p for p in re.findall(r"[^.\[\]]+", loc)
            )
        if err["type"] == "extra_forbidden":
            closest = _closest_key(raw_loc)
            if closest is not None:
                msg += f"; did you mean {closest}?"
        variable = _env_variable(raw_loc)
        if variable is not None and loc:
            loc += f" (from ${variable})"
        if not loc:  # a cross-section check whose message names the keys itself
            lines.append(msg)
        elif err["type"] in {"missing"} or isinstance(got, dict):
            lines.append(f"{loc}: {msg}")
        else:
            lines.append(f"{loc}: {msg} (got {got!r})")
    return lines


def parse_config(data: dict[str, Any]) -> Settings:
    """Validate an already-parsed TOML document (plus environment overrides)."""
    try:
        return Settings(**data)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc)) from None


def load_config(path: str | os.PathLike[str]) -> Settings:
    """Read and validate a config file; a missing or unreadable file is a ConfigError too."""
    p = Path(path)
    try:
        # a FIFO would block for ever, /dev/zero would fill the memory: a regular file only
        raw = read_regular_file(p, CONFIG_MAX_BYTES)
    except UnreadableFile as exc:
        problem = str(exc)
        if problem == "file not found":
            problem = "config file not found"
        elif problem.startswith("cannot read the file"):
            problem = problem.replace("cannot read the file", "cannot read config file")
        else:
            problem = f"the config must be a regular file of at most {CONFIG_MAX_BYTES} bytes: " \
                      f"{problem}"
        raise ConfigError([f"{p}: {problem}"]) from None
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError([f"{p}: not valid TOML: {exc}"]) from None
    if not data:
        # every table has defaults, so an empty file would validate as a demo seeder on
        # /dev/ttyUSB0: almost certainly the wrong file, or one never filled in
        raise ConfigError([
            f"{p}: the config file is empty: it needs at least [machine] with this seeder's "
            "id and rows, and the tables of the parts it has ([rs485] port, [gnss], "
            "[mqtt], ...); examples/sowgate.toml shows every table"])
    return parse_config(resolve_relative_paths(data, p.parent))


# The keys that name files: a relative value is from the config file's directory (a config
# that names its prescription map next to it works from any working directory, as a systemd
# unit's does). Values from the environment stay as given (the caller's working directory).
FILE_KEYS: tuple[tuple[str, ...], ...] = (
    ("store", "path"),
    ("prescription", "path"),
    ("prescription", "as_applied_path"),
    ("mqtt", "password_file"),
    ("mqtt", "tls", "ca_file"),
    ("mqtt", "tls", "cert_file"),
    ("mqtt", "tls", "key_file"),
    ("dashboard", "password_file"),
)


def resolve_relative_paths(data: dict[str, Any], base: Path) -> dict[str, Any]:
    """A copy of a parsed config file with its relative ``FILE_KEYS`` made absolute against
    ``base`` (the file's directory). Tables are copied on the way down, so the caller's document
    stays as parsed; anything not a relative path (absolute, ``~``, not a string) is left for
    validation to judge."""
    out = dict(data)
    for key in FILE_KEYS:
        table = out
        for name in key[:-1]:
            inner = table.get(name)
            if not isinstance(inner, dict):
                break
            table[name] = table = dict(inner)
        else:
            value = table.get(key[-1])
            if (isinstance(value, str) and value and not value.startswith("~")
                    and not Path(value).is_absolute()):
                table[key[-1]] = str((base / value).absolute())
    return out


STORE_FILE = "records.sqlite3"
AS_APPLIED_FILE = "as_applied.csv"


def store_path(settings: Settings, state: Path | None = None) -> Path:
    """The record store: ``store.path``, else ``records.sqlite3`` in the state directory."""
    if settings.store.path:
        return Path(settings.store.path)
    return (state if state is not None else state_dir()) / STORE_FILE


def as_applied_path(settings: Settings, state: Path | None = None) -> Path:
    """The as-applied log: ``prescription.as_applied_path``, else one in the state directory."""
    if settings.prescription.as_applied_path:
        return Path(settings.prescription.as_applied_path)
    return (state if state is not None else state_dir()) / AS_APPLIED_FILE


def state_dir() -> Path:
    """Persistent state: SOWGATE_STATE_DIR, else systemd STATE_DIRECTORY, else ./sowgate-state.

    Only the path; ``prepare_state_dir`` creates it and checks it at start."""
    return resolve_state_dir()[0]
