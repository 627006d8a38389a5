"""Two daemons on one state directory mixed two machines' records with no warning (issue 20,
item 9): the second ``sowgate run`` now stops at once, exit 78, naming the directory and the pid
of the daemon that holds it; once that one is gone the directory is free again (the kernel's
lock goes with the process: no stale lock after a crash)."""

from __future__ import annotations

import asyncio
import signal
from pathlib import Path

from tests.helpers import eventually, run_sowgate, sowgate_env, sowgate_process

CONFIG = '[machine]\nid = "{mid}"\n[rs485]\nport = "{tmp}/no-such-tty"\n'


async def test_a_second_daemon_on_one_state_directory_exits_78_naming_the_holder(
    tmp_path: Path,
) -> None:
    state = tmp_path / "state"
    first_cfg, second_cfg = tmp_path / "a.toml", tmp_path / "b.toml"
    first_cfg.write_text(CONFIG.format(mid="seeder-a", tmp=tmp_path))
    second_cfg.write_text(CONFIG.format(mid="seeder-b", tmp=tmp_path))
    env = sowgate_env(state, clean=True)
    lock = state / "sowgate.lock"
    async with sowgate_process("run", "--config", str(first_cfg), env=env) as first:
        await eventually(lambda: lock.exists() and lock.read_text().strip() == str(first.pid),
                         60.0, "the first daemon holds the state directory")
        second = await asyncio.to_thread(run_sowgate, "run", "--config", str(second_cfg),
                                         env=env)
        assert second.returncode == 78, second.stderr
        assert second.stderr.startswith(
            f"state directory: {str(state)!r} is in use by another sowgate daemon (pid "
            f"{first.pid}, holding sowgate.lock)"), second.stderr
        assert first.returncode is None  # the first one runs on, undisturbed
        first.send_signal(signal.SIGKILL)  # as a crash would: no clean release
        await first.wait()
    async with sowgate_process("run", "--config", str(second_cfg), env=env) as again:
        await eventually(lambda: lock.read_text().strip() == str(again.pid), 60.0,
                         "the directory taken over after the holder died")
        again.terminate()
        await again.wait()
