"""The fault matrix's rows: each a fault, how it is injected and the invariant that must hold,
with the figures the invariants are stated in.

The faults are injected and measured by the groups in ``recording_faults``, ``device_faults``
and ``input_faults`` (run by ``matrix.run_campaign``); ``test_fault_matrix.py`` judges each
row and ``report.py`` renders docs/reliability.md from the same results.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from gateway.config import EXIT_CONFIG

REPO = Path(__file__).resolve().parents[2]
EXAMPLE_CONFIG = REPO / "examples" / "sowgate.toml"

# ---- figures the invariants are stated in ---------------------------------------------------
KILLS = 10
# What a SIGKILL may take with it: a seed is committed at the recorder's next flush (every
# store.commit_interval_s, 0.5 s) once its bracketing GNSS epoch is in, which it waits for at
# most positioning.pending_timeout_s (0.5 s). Seeds sensed longer ago than this are durable.
COMMIT_WINDOW_S = 0.5 + 0.5
BROKER_DOWN_S = 60.0
DISK_FULL_S = 20.0
# Motor duty: "no overshoot" means never above the highest steady duty by more than this
# (the radar's 3 % noise through the speed filter moves the duty by about ±1.5 points).
DUTY_TOLERANCE_PCT = 3.0
MODBUS_FAULT_S = 5.0
AFTER_FAULT_S = 6.0
SPEED_GAP_S = 1.0
RECOVERY_MAX_S = 6.0  # after the fault ends the duty is back at steady within this
# issue 11 item 4: the PWM module stops itself when sowgate has not written it for
# [actuators] comm_timeout_s (default 2 s); the margin is one poll period and a sample
COMM_TIMEOUT_S = 2.0
MOTOR_STOPPED_WITHIN_S = COMM_TIMEOUT_S + 1.0
FUZZ_S = 5.0
# A fuzzed line may not flood the journal: warnings about it are rate-limited with a count.
LOG_LINES_PER_FUZZ_MAX = 10
RSS_GROWTH_MAX_MB = 30.0
BINARY_LOG_BYTES = 1100  # binary receiver output between two sentences (over a line's limit)
# the store's medium (issue 20 items 5-7)
LAST_WRITES_LOST_S = 3.0  # an SD card whose cache lied about its last seconds of writes
FREEZE_S = 8.0  # the state directory's file system frozen (a card that stalls)
FREEZE_SETTLE_S = 5.0  # sowing before the steady duty is measured (the controller settles)
ROLLOVER_WEEKS = 1024  # a receiver past a GPS week rollover dates everything this far back
STORE_DAMAGE_ROWS = ("store_wal_lost", "store_last_writes_lost", "store_zero_length",
                     "store_truncated", "store_page_overwritten")
# the hopper scale rows: a wheat drill 8 % off its model, the correction learnt first
HOPPER_BIAS = 0.08
HOPPER_LEARN_MAX_S = 120.0
HOPPER_FAULT_S = 6.0  # longer than the 2 s after which a silent device is alarmed
HOPPER_JUMP_KG = 250.0
# the correction may move only by what a window fitted on both sides of the fault adds
HOPPER_FACTOR_TOLERANCE = 0.002
# GNSS time rows (issue 20 item 4): each fault's window of seeds is judged
GNSS_TIME_WINDOW_S = 6.0
# a seed is where it landed to within this (RTK noise plus the seed line's arrival jitter on
# a loaded host: up to ~0.2 m at 8 km/h; a stamp 1 s off or a cluster: metres)
GNSS_TIME_POSITION_M = 0.5
# a step is taken after gnss_time.STEP_CONFIRM_EPOCHS (0.5 s): its seeds may be extrapolated
GNSS_STEP_EXTRAPOLATED_S = 1.0
# a scale that gives no usable reading (silent, NaN, out of range) freezes the correction: it
# may not move at all, through the fault and the seconds after (issue 21: it moved 0.0045)
HOPPER_FROZEN_FAULTS = ("silent", "nan", "out_of_range")


# the seed-row rows (issue 20 items 2 and 3), on the simulated 6-row planter at 8 km/h
ROW_SILENT_S = 15.0
SILENT_ROW = 3
# [row_monitor] delay_s (5 s) + a flush and a state message, with room for a busy machine
ROW_ALARM_WITHIN_S = 10.0
CHATTER_ROW = 2
CHATTER_LINES_PER_S = 2300
CHATTER_S = 10.0
# the AgOpenGPS row: AgIO says 8 km/h at 10 Hz; a stranger sends this many frames of 30 km/h
# (all sections on) per AgIO frame, plus junk, and AgIO's line one bad checksum per tick
AGOPENGPS_KMH = 8.0
STRANGER_FRAMES_PER_TICK = 50
# the farm server rows (issue 24 §4): real daemons on the simulated 6-row planter at 8 km/h
# (~65 seeds/s a cab: the daemon's real rate on this planter), `[mqtt] farm_server_ack` with
# its resend timeout at this (the default is 60 s; 2 s makes a row's minute hold ~30 of them)
FARM_ACK_TIMEOUT_S = 2.0
FARM_PG_DOWN_S = 30.0
# SOWGATE_FARM_FULL_SCALE=1: the issue's own sizes (ten cabs, ten minutes offline), a run of
# about 13 minutes outside `make test` (docs/farm-server.md has its result)
FARM_FULL_SCALE = os.environ.get("SOWGATE_FARM_FULL_SCALE", "") not in ("", "0")
FARM_PG_CABS = 10 if FARM_FULL_SCALE else 3  # make test: scaled to what a busy 2-core box carries
FARM_INGEST_KILLS = 5
FARM_DUPLICATE_COPIES = 10
FARM_REPLAY_EVERY = 10
FARM_FLOOD_BATCHES = 20  # the pass ends once this many of the cab's batches were flooded
# make test: the 10 minutes offline scaled down 15x: still 20 resend timeouts, ~2 600
# records held
FARM_OFFLINE_S = 600.0 if FARM_FULL_SCALE else 40.0


@dataclass(frozen=True)
class Row:
    name: str
    group: str
    injected: str
    invariant: str


ROWS: tuple[Row, ...] = (
    Row("sigkill_during_seeding_x10", "kills",
        f"SIGKILL the daemon {KILLS}× while seeding (~2–3 s of seeds each time), restarted at "
        "once on the same store",
        "`integrity_check` ok after every kill; ids contiguous within each run and above "
        "every earlier id (never reused); per kill, records lost "
        f"≤ seeds sensed in the last {COMMIT_WINDOW_S:g} s (the commit window)"),
    Row("broker_down_60s", "broker",
        f"mosquitto stopped for {BROKER_DOWN_S:g} s while seeding, then started again",
        "the store keeps recording; every seed edge becomes a record; every stored id is "
        "delivered; daemon never exits"),
    Row("disk_full_20s", "disk",
        f"state dir on a 2 MiB tmpfs, filled to the last byte for {DISK_FULL_S:g} s, then "
        "remounted 64 MiB",
        "every seed edge becomes a record (none lost); `records.store_failed` published on "
        "MQTT while full; ids contiguous; integrity ok"),
    *(
        Row(name, "store",
            f"SIGKILL while seeding, then {how}, then the daemon started again on that state",
            f"daemon up, no traceback; no id published for two different seeds (new ids above "
            f"every id stored or published before); `{alarm}` on MQTT; the motor duty back at "
            f"steady ≤ {RECOVERY_MAX_S:g} s after the seed port opens{kept}")
        for name, how, alarm, kept in (
            ("store_wal_lost", "the WAL (and -shm) deleted (what a power cut can take)",
             "store.unclean_stop", ""),
            ("store_last_writes_lost", f"the whole state dir put back as it was "
             f"{LAST_WRITES_LOST_S:g} s before the cut (a card whose cache lied)",
             "store.unclean_stop` (or `store.replaced", ""),
            ("store_zero_length", "the store emptied to a zero-length file", "store.replaced",
             "; the file kept as records.sqlite3.bad-<time>"),
            ("store_truncated", "the store truncated to half its size", "store.replaced",
             "; the file kept as records.sqlite3.bad-<time>"),
            ("store_page_overwritten", "one 4 KiB page in the middle of the store overwritten",
             "store.replaced", "; the file kept as records.sqlite3.bad-<time>"),
        )
    ),
    Row("store_prune_gps_rollover", "rollover",
        f"the receiver's dates {ROLLOVER_WEEKS} weeks early (a GPS week rollover) while "
        "seeding, every record delivered, then a restart (which prunes) with 30 days' retention",
        "no record deleted (pruning counts age back from the earlier of the host clock and the "
        "newest record's own time, never from one clock alone); daemon up, no traceback"),
    Row("store_frozen_8s", "freeze",
        f"state dir on a loop-mounted ext4 image, `fsfreeze --freeze` for {FREEZE_S:g} s at a "
        "steady 8 km/h, then thawed",
        f"the motor duty never below steady min − {DUTY_TOLERANCE_PCT:g} points while frozen "
        f"(steady: the 4 s before the freeze, after {FREEZE_SETTLE_S:g} s of sowing) "
        "(control never waits for the card); `store.stalled` on MQTT while frozen; every seed "
        "edge becomes a record; ids unique, contiguous; integrity ok; no traceback"),
    *(
        Row(f"modbus_radar_{fault}", "modbus",
            f"radar (id 1): {how} for {MODBUS_FAULT_S:g} s at a steady 8 km/h",
            "daemon up, no traceback; motor duty during and after ≤ steady max + "
            f"{DUTY_TOLERANCE_PCT:g} points; back at steady ≤ {RECOVERY_MAX_S:g} s after; "
            "metering never stops without an alarm on MQTT")
        for fault, how in (
            ("silent", "no reply at all"),
            ("crc", "every reply with a wrong CRC"),
            ("wrong_id", "every reply from another device id (valid CRC)"),
            ("exception", "every reply a Modbus exception (device failure)"),
            ("truncated", "every reply loses its last 3 bytes"),
            ("noise", "5 bytes of line noise ahead of every reply and one of its bytes hit"),
        )
    ),
    Row("radar_speed_gap_1s", "modbus",
        f"the radar reads 0 km/h for {SPEED_GAP_S:g} s at a steady 8 km/h (valid replies), then "
        "8 km/h again",
        f"motor duty after the gap ≤ steady max + {DUTY_TOLERANCE_PCT:g} points (no "
        f"overshoot); back at steady ≤ {RECOVERY_MAX_S:g} s; daemon up, no traceback"),
    Row("modbus_port_vanished", "modbus",
        f"the RS485 adapter unplugged for {MODBUS_FAULT_S:g} s (port path gone, fd EIO), "
        "then plugged back",
        f"the PWM module's motor output is 0 within {MOTOR_STOPPED_WITHIN_S:g} s (module "
        f"comm-loss timeout {COMM_TIMEOUT_S:g} s); `pwm.unavailable` on MQTT; after replug back "
        f"at steady ≤ {RECOVERY_MAX_S:g} s without overshoot"),
    *(
        Row(f"hopper_scale_{fault}", "hopper",
            f"hopper scale (id 4): {how} for {HOPPER_FAULT_S:g} s while seeding wheat at 5 km/h "
            f"with a drill {HOPPER_BIAS:.0%} off its model, the correction learnt",
            f"{then}; the daemon sows on (duty within steady ± {DUTY_TOLERANCE_PCT:g} points); "
            + ("the published `discharge_correction` does not move (frozen: no usable reading "
               "for 2 s ends the fit's line)" if fault in HOPPER_FROZEN_FAULTS else
               f"the published `discharge_correction` moves ≤ {HOPPER_FACTOR_TOLERANCE:g}")
            + "; daemon up, no traceback")
        for fault, how, then in (
            ("silent", "no reply at all",
             "`hopper_scale.unavailable` on MQTT, cleared when it answers again"),
            ("nan", "a float32 NaN in every reply (a broken load cell)",
             "`hopper_scale.bad_reading` on MQTT counting the rejected readings (≥ 2), none "
             "fed to the fit; cleared after 10 good readings in a row"),
            ("out_of_range", "1e7 kg in every reply (an overload code, beyond 120 % of "
             "capacity)",
             "`hopper_scale.bad_reading` on MQTT counting the rejected readings, none fed to "
             "the fit; cleared after 10 good readings in a row"),
            ("jump", f"the weight {HOPPER_JUMP_KG:g} kg lower (a load cell slipping), then back",
             "`hopper_scale.jump` on MQTT (no meter empties that in seconds: not seed); the "
             "fit restarts its line"),
        )
    ),
    *(
        Row(f"gnss_{fault}", "gnss_time",
            f"{how}, while sowing at 8 km/h (the simulated UM982's sentences and heading log "
            "alike)",
            f"every seed of the {GNSS_TIME_WINDOW_S:g} s after it stored, stamped {stamped}, "
            f"within {GNSS_TIME_POSITION_M:g} m of where it landed (no cluster), {extrap}; "
            f"`gnss.{alarm}` on MQTT; daemon up, no traceback")
        for fault, how, stamped, extrap, alarm in (
            ("two_epochs_2h_ahead", "two epochs stamped 2 h ahead, then correct time",
             "in true time (none in the future)", "none extrapolated", "time_outlier"),
            ("time_step_back_1h", "the receiver's time steps back 1 h for good",
             "in the receiver's new time",
             f"none extrapolated but in the {GNSS_STEP_EXTRAPOLATED_S:g} s of the step",
             "time_step"),
            ("week_rollover", f"dates 1024 weeks early (GPS week rollover) for "
             f"{GNSS_TIME_WINDOW_S:g} s", "with the true date (2026, not 2007)",
             "none extrapolated", "week_rollover"),
            ("leap_second", "a UTC leap second: 23:59:60.00–.90 (`235960.00`), then 00:00:00",
             "in UTC (those in the leap second 23:59:59.999999)", "none extrapolated",
             "leap_second"),
        )
    ),
    Row("seed_row_silent_15s", "rows",
        f"row {SILENT_ROW}'s seed tube sends nothing for {ROW_SILENT_S:g} s while sowing at "
        "8 km/h (a blocked tube), then sows again",
        f"`row.{SILENT_ROW}.blocked` on MQTT within {ROW_ALARM_WITHIN_S:g} s, no other row "
        "alarmed, cleared once it sows again; every seed sent stored; daemon up, no traceback"),
    Row("seed_rows_all_silent_15s", "rows",
        f"every row silent for {ROW_SILENT_S:g} s while sowing at 8 km/h with the meter "
        "turning (~1 000 seeds not sent)",
        f"`seed_sensors.all_rows_silent` (critical) on MQTT within {ROW_ALARM_WITHIN_S:g} s, "
        "no row blamed on its own, cleared once seeds come; daemon up, no traceback"),
    Row("seed_row_chatter", "rows",
        f"row {CHATTER_ROW}'s sensor sends {CHATTER_LINES_PER_S} valid lines a second for "
        f"{CHATTER_S:g} s while sowing (a chattering sensor)",
        f"`row.{CHATTER_ROW}.chattering` and `seed_sensors.implausible_rate` on MQTT; none of "
        "the chatter stored as seeds; its edges counted in `state.row_monitor.rows."
        f"{CHATTER_ROW}.implausible_edges`; the other rows' seeds all stored; no traceback"),
    Row("agopengps_stranger_flood", "agopengps",
        f"AgOpenGPS (through a fake AgIO on loopback UDP) is the speed source at "
        f"{AGOPENGPS_KMH:g} km/h; for {FUZZ_S:g} s a stranger (127.0.0.2) sends "
        f"{STRANGER_FRAMES_PER_TICK} well-formed frames of 30 km/h and random bytes per AgIO "
        "frame, and AgIO's own line a frame with a bad checksum each tick",
        f"duty unchanged (within steady ± {DUTY_TOLERANCE_PCT:g} points); ≤ "
        f"{LOG_LINES_PER_FUZZ_MAX} log lines; daemon up, no traceback"),
    Row("serial_fuzz_hmi", "serial",
        f"{FUZZ_S:g} s of random bytes (64 B every 50 ms) on the touchscreen line",
        f"daemon up, no traceback; duty unchanged (≤ steady max + {DUTY_TOLERANCE_PCT:g}); "
        f"≤ {LOG_LINES_PER_FUZZ_MAX} log lines of the daemon's own (pymodbus's own, e.g. its "
        f"\"Repeating....\" under load, not counted); RSS growth ≤ {RSS_GROWTH_MAX_MB:g} MB"),
    Row("serial_fuzz_gnss", "serial",
        f"{FUZZ_S:g} s of {BINARY_LOG_BYTES} B of binary output (no line end) before every "
        "sentence on the GNSS line",
        "daemon up, no traceback; the valid sentences after the binary are kept: every seed "
        f"of the window RTK-fixed, none extrapolated; ≤ {LOG_LINES_PER_FUZZ_MAX} log lines of "
        "the daemon's own"),
    Row("serial_fuzz_seed_line", "serial",
        f"{FUZZ_S:g} s of random junk lines (1–200 B + CRLF every 50 ms) between the seed lines",
        "daemon up, no traceback; every valid seed line becomes a record; "
        f"≤ {LOG_LINES_PER_FUZZ_MAX} log lines of the daemon's own; RSS growth ≤ "
        f"{RSS_GROWTH_MAX_MB:g} MB"),
    Row("command_fuzz", "commands",
        "hostile payloads on every `cmd/<name>` (nesting 2000 deep, wrong types, numbers as "
        "strings, NaN, invalid UTF-8, random bytes, unknown names) plus random JSON",
        "one error ack per command; the MQTT session never restarts; strict types "
        "(`\"6\"` is not a rate); daemon up, no traceback"),
    Row("config_fuzz_values", "config",
        "every key of examples/sowgate.toml given a wrong type, ±1e9, plus an unknown key "
        "per table and broken TOML; `sowgate check-config` for each, `sowgate run` for "
        "the first rejected one of each table",
        f"exit 0 (accepted) or {EXIT_CONFIG} naming the key (or the TOML line); the wrong "
        "type and unknown keys always rejected; never a traceback"),
    Row("config_fuzz_files", "config",
        "a missing `mqtt.tls.ca_file`, a missing `mqtt.password_file`, a state dir that is "
        "a file",
        f"`sowgate run` exits {EXIT_CONFIG} naming the key within 10 s; `check-config` "
        f"exits {EXIT_CONFIG} for the config file keys; never a traceback"),
    Row("farm_postgres_down", "farm",
        f"a private PostgreSQL 15 cluster (initdb, own port) stopped for {FARM_PG_DOWN_S:g} s "
        f"(`pg_ctl stop -m fast`) while {FARM_PG_CABS} cabs seed into one `sowgate ingest`, "
        "then started again",
        "ingest keeps running; afterwards every record of every cab in the database exactly "
        "once (ids compared with each cab's store) and the retained `<prefix>/<machine>/"
        "ingested` watermark equal to the cab's last id; daemons never exit on their own, "
        "no traceback"),
    Row("farm_ingest_sigkill_x5", "farm",
        f"two `sowgate ingest` processes in one share group; SIGKILL {FARM_INGEST_KILLS}×, "
        "alternating, at any phase of a flush (each restarted at once) while a cab seeds",
        "every record in the database exactly once; the retained watermark equal to the "
        "cab's last id; the cab never exits on its own, no traceback"),
    Row("farm_broker_restart_no_persistence", "farm",
        "mosquitto (persistence off) restarted while a cab seeds: the retained watermark, the "
        "sessions and every in-flight message lost",
        "every record in the database exactly once; the watermark retained again, equal to "
        "the cab's last id; daemon never exits on its own, no traceback"),
    Row("farm_duplicate_flood", "farm",
        f"every `seeds` batch the cab publishes published {FARM_DUPLICATE_COPIES}× more (as "
        f"the cab), the last {FARM_REPLAY_EVERY} replayed at every {FARM_REPLAY_EVERY}th, "
        f"all of them once more after the pass ({FARM_FLOOD_BATCHES} batches at least); and "
        "the cab's own resends",
        "no record twice in the database, none missing; the retained watermark equal to the "
        "cab's last id; daemon never exits on its own, no traceback"),
    Row("farm_cab_offline", "farm",
        f"the cab's link to the broker cut (a TCP relay drops its connections and refuses "
        f"new ones) for {FARM_OFFLINE_S:g} s while it seeds"
        + ("" if FARM_FULL_SCALE else ": the issue's 10 minutes scaled down 15×")
        + f", {FARM_OFFLINE_S / FARM_ACK_TIMEOUT_S:g}× the cab's "
        f"`farm_server_ack_timeout_s` ({FARM_ACK_TIMEOUT_S:g} s)",
        "the records of the outage held in the cab's store and published from the oldest "
        "uncovered one when it is back; every record in the database exactly once; the "
        "retained watermark equal to the cab's last id; daemon never exits on its own, "
        "no traceback"),
)
ROWS_BY_NAME = {r.name: r for r in ROWS}


