"""Whether a process is alive. No numpy here: the worker pool's forkserver imports this (through
:mod:`kinreg.run.executor`) before it limits the BLAS threads, which must happen before numpy loads."""

from __future__ import annotations

import os


def process_alive(pid: int) -> bool:
    """Whether a process with this pid exists (one of another user counts as alive)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
