"""The stage cache: each stage's output kept in the output folder under a key of its inputs.

A re-run looks every stage up by its key and re-does only what changed; a killed run leaves
either a complete entry or none, so a restart continues where it stopped and gives the same
result as an uninterrupted run.

Layout: ``<folder>/<stage>/<key>.npz`` (plain numeric and string arrays, ``np.savez``) and
``<key>.json`` (schema version, stage, key, the npz's size and sha256, small metadata). The JSON
sidecar is renamed into place last and is the commit mark: an npz without it is ignored. No
pickle anywhere: the output folder is the user's, and loading it must never run code, so arrays
are loaded with ``allow_pickle=False`` and kinreg's types go through the explicit converters
in :mod:`kinreg.run.codecs`. This module knows no kinreg types.

Keys (:meth:`StageCache.key`) are sha256 over a stable serialisation of the parts:

- a config section (a dataclass): ``dataclasses.asdict`` as JSON with sorted keys, enums by value;
- an input file (a :class:`pathlib.Path`): its absolute path, size and ``mtime_ns``. That costs a
  ``stat`` instead of reading gigabytes; the price is that a file replaced by different content
  with the same size and modification time (``cp -p``, ``rsync -t`` of an edited file of equal
  length) is not noticed. Pass ``str(path)`` for a path that is a name, not an input;
- a numpy array: dtype, shape and the raw bytes; an object with ``cache_key_parts()`` (a
  :class:`~kinreg.geometry.Pose`): those parts;
- plain values (str, int, float including nan/inf, bool, None, lists, tuples, dicts) as JSON.

Every key also covers :data:`CACHE_SCHEMA_VERSION` and the kinreg version, so results of an
older kinreg are not reused. Bump :data:`CACHE_SCHEMA_VERSION` when a stored layout changes, or
when a stage's results change without a change of the kinreg version (development builds).
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import json
import logging
import os
import shutil
import zipfile
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePath
from typing import Any

import numpy as np

from kinreg._version import __version__
from kinreg.errors import OutputError
from kinreg.run.liveness import process_alive

log = logging.getLogger(__name__)

# Bump when a stored layout or the meaning of a key part changes (old entries are then ignored).
CACHE_SCHEMA_VERSION = 4

Arrays = dict[str, np.ndarray]  # what a cache entry holds


@dataclass(frozen=True)
class CacheEntry:
    """A loaded entry: its arrays and the small JSON metadata stored with them."""

    arrays: Arrays
    meta: dict[str, Any]


class StageCache:
    """Stage outputs in ``folder`` (created on the first store), keyed by their inputs."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)

    # ------------------------------------------------------------------ keys

    def key(self, stage: str, *parts: Any) -> str:
        """The hex sha256 of ``stage`` and ``parts`` (see the module docstring for how each kind
        of part is serialised). Raises :class:`TypeError` for a part it cannot serialise stably
        and :class:`OutputError` for an input file that does not exist."""
        h = hashlib.sha256()
        _feed(h, ["kinreg-cache", CACHE_SCHEMA_VERSION, __version__, stage])
        for part in parts:
            _feed(h, part)
        return h.hexdigest()

    # ------------------------------------------------------------------ entries

    def _paths(self, stage: str, key: str) -> tuple[Path, Path]:
        if not stage or "/" in stage or stage.startswith(".") or not key.isalnum():
            raise ValueError(f"bad stage or key: {stage!r}, {key!r}")
        folder = self.folder / stage
        return folder / f"{key}.npz", folder / f"{key}.json"

    def load(self, stage: str, key: str) -> CacheEntry | None:
        """The entry stored under ``stage``/``key``, or ``None`` when there is none (or it is
        incomplete, of another schema version, or damaged: then it is logged and ignored)."""
        npz_path, json_path = self._paths(stage, key)
        if not json_path.is_file():
            return None
        try:
            sidecar = json.loads(json_path.read_text(encoding="utf-8"))
            if (sidecar.get("schema_version") != CACHE_SCHEMA_VERSION or sidecar.get("stage") != stage
                    or sidecar.get("key") != key):
                return None
            data = npz_path.read_bytes()
            if len(data) != sidecar["npz_size"] or hashlib.sha256(data).hexdigest() != sidecar["npz_sha256"]:
                log.warning("%s: damaged cache entry ignored", npz_path)
                return None
            with np.load(npz_path, allow_pickle=False) as npz:
                arrays = {name: npz[name] for name in npz.files}
        except (OSError, ValueError, KeyError, TypeError, zipfile.BadZipFile) as e:
            log.warning("%s: unreadable cache entry ignored (%s)", json_path, e)
            return None
        return CacheEntry(arrays, sidecar.get("meta", {}))

    def store(self, stage: str, key: str, arrays: Mapping[str, np.ndarray],
              meta: Mapping[str, Any] | None = None) -> None:
        """Store ``arrays`` (numeric, bool or fixed-width string; no object arrays) and ``meta``
        (JSON-able) under ``stage``/``key``, atomically: an interruption at any point leaves the
        previous state (no entry, or the old one). Raises :class:`TypeError` for an object array
        or non-JSON meta, :class:`OutputError` when the folder cannot be written."""
        for name, a in arrays.items():
            if np.asarray(a).dtype.hasobject:
                raise TypeError(f"cache array {name!r} has dtype object; convert it to plain arrays first")
        meta_json = json.dumps(dict(meta or {}), sort_keys=True)  # fails before anything is written
        npz_path, json_path = self._paths(stage, key)
        try:
            npz_path.parent.mkdir(parents=True, exist_ok=True)
            with _atomic(npz_path) as tmp, open(tmp, "wb") as f:
                np.savez(f, **{name: np.asarray(a) for name, a in arrays.items()})  # type: ignore[arg-type]
                f.flush()
                os.fsync(f.fileno())
            data = npz_path.read_bytes()
            sidecar = (f'{{"schema_version": {CACHE_SCHEMA_VERSION}, "stage": {json.dumps(stage)}, '
                       f'"key": "{key}", "npz_size": {len(data)}, '
                       f'"npz_sha256": "{hashlib.sha256(data).hexdigest()}", "meta": {meta_json}}}\n')
            with _atomic(json_path) as tmp:
                tmp.write_text(sidecar, encoding="utf-8")
        except OSError as e:
            raise OutputError(f"cannot write the stage cache: {e.strerror or e}", npz_path) from None

    def prune(self, keep: Iterable[tuple[str, str]]) -> int:
        """Delete every committed entry (and large-output folder) whose ``(stage, key)`` is not
        in ``keep``; return how many were deleted. Files that are not cache entries are left."""
        keep = set(keep)
        removed = 0
        if not self.folder.is_dir():
            return 0
        for stage_dir in self.folder.iterdir():
            if not stage_dir.is_dir() or stage_dir.name.startswith("."):
                continue
            for path in stage_dir.iterdir():
                key = path.name.split(".", 1)[0]
                if path.name.startswith(".") or not key.isalnum() or (stage_dir.name, key) in keep:
                    continue
                if path.is_dir() and not path.is_symlink():
                    shutil.rmtree(path, ignore_errors=True)
                elif path.suffix in (".npz", ".json"):
                    path.unlink(missing_ok=True)
                else:
                    continue
                removed += path.suffix != ".npz"  # one per entry: its sidecar (or its folder)
        return removed

    def remove_stale(self) -> None:
        """Delete temporary files left by killed runs (``.*.tmp-<pid>`` of dead processes)."""
        if not self.folder.is_dir():
            return
        for path in [*self.folder.glob(".*.tmp-*"), *self.folder.glob("*/.*.tmp-*")]:
            pid = path.name.rsplit("-", 1)[-1]
            if pid.isdigit() and not process_alive(int(pid)):
                if path.is_dir():
                    shutil.rmtree(path, ignore_errors=True)
                else:
                    path.unlink(missing_ok=True)



@contextmanager
def _atomic(path: Path) -> Iterator[Path]:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


# --------------------------------------------------------------------------- key serialisation


def _token(h: Any, tag: bytes, payload: bytes) -> None:
    # Length-prefixed, so that no two different part sequences feed the same bytes.
    h.update(tag + len(payload).to_bytes(8, "little"))
    h.update(payload)


def _plain(x: Any) -> Any:
    """A JSON-able, order-stable form of config values."""
    if isinstance(x, enum.Enum):
        return {"__enum__": type(x).__name__, "value": _plain(x.value)}
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return {"__dataclass__": type(x).__qualname__,
                **{f.name: _plain(getattr(x, f.name)) for f in dataclasses.fields(x)}}
    if isinstance(x, Mapping):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, PurePath):
        return {"__path__": str(x)}
    if isinstance(x, np.generic):
        return x.item()
    if x is None or isinstance(x, (str, bool, int, float)):
        return x
    raise TypeError(f"cannot build a cache key from {type(x).__name__}")


def _feed(h: Any, part: Any) -> None:
    if isinstance(part, Path):
        resolved = part.resolve()
        try:
            st = resolved.stat()
        except OSError as e:
            raise OutputError(f"cannot fingerprint the input: {e.strerror or e}", part) from None
        _token(h, b"F", json.dumps([str(resolved), st.st_size, st.st_mtime_ns]).encode())
    elif isinstance(part, np.ndarray):
        if part.dtype.hasobject:
            raise TypeError("cannot build a cache key from an object array")
        a = np.ascontiguousarray(part)
        _token(h, b"A", json.dumps([a.dtype.str, list(a.shape)]).encode())
        _token(h, b"B", a.tobytes())
    elif hasattr(part, "cache_key_parts"):  # e.g. a Pose: its arrays
        _token(h, b"P", b"")
        for piece in part.cache_key_parts():
            _feed(h, piece)
    elif isinstance(part, bytes):
        _token(h, b"R", part)
    else:
        _token(h, b"J", json.dumps(_plain(part), sort_keys=True, allow_nan=True).encode())


# --------------------------------------------------------------------------- converters


