"""Whether a process is alive. No numpy here: the worker pool's forkserver imports this (through
:mod:`kinreg.run.executor`) before it limits the BLAS threads, which must happen before numpy loads."""

from __future__ import annotations

import os


def process_alive(pid: int) -> bool:
    """Whether a process with this pid is running (one of another user counts as alive). A
    zombie, ended but not yet reaped by its parent, has ended: a killed ``kinreg`` stays one
    until whoever started it waits for it, and its workers must not take it for alive then."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat = f.read()
    except OSError:  # no /proc (macOS), or it ended since
        return True
    return stat[stat.rindex(b")") + 2:][:1] not in (b"Z", b"X")  # the state, after "pid (name) "
