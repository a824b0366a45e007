"""Atomic output: write under a temporary name in the target folder, rename when complete.

An interrupted run never leaves a file that looks finished: the final name appears only through
``os.replace`` after the content is fully written.
"""

from __future__ import annotations

import errno
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from kinreg.errors import OutputError


def check_writable_target(path: Path, overwrite: bool) -> None:
    """Refuse an existing target (unless ``overwrite``) and an unwritable folder, up front."""
    if path.exists() and not overwrite:
        raise OutputError("exists; use --overwrite to replace it", path)
    if path.exists() and path.is_dir():
        raise OutputError("is a folder", path)
    parent = path.parent if str(path.parent) else Path(".")
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"cannot create the folder: {e.strerror or e}", parent) from None
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError("folder is not writable", parent)


def temporary_name(path: Path) -> Path:
    """The hidden temporary name used while ``path`` is being written; it keeps the suffix,
    from which some writers pick the format."""
    return path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")


@contextmanager
def atomic_path(path: str | os.PathLike[str], overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary path to write to; rename it to ``path`` if the block succeeds.

    On any exception the temporary file is removed and the exception propagates (``OSError``
    becomes :class:`OutputError`, with disk-full named as such).
    """
    target = Path(path)
    check_writable_target(target, overwrite)
    tmp = temporary_name(target)
    try:
        yield tmp
        os.replace(tmp, target)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        if e.errno == errno.ENOSPC:
            raise OutputError("disk full while writing", target) from None
        raise OutputError(f"cannot write: {e.strerror or e}", target) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
