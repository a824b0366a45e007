"""Resumable ``kinreg process``: the output folder's stage cache and the rules around it.

Every ``kinreg process`` run keeps its stage results in ``<out>/.kinreg-cache/`` (a
:class:`~kinreg.run.stage_cache.StageCache`: plain arrays and JSON, no pickle). A later run with
``--resume`` looks each stage up under a key of its inputs and re-does only what changed:

- ``slice``: the index of the quasi-static scans (windows, point counts, summary), keyed by the
  trajectory and cloud files (path, size, modification time), ``[slicing]`` (not ``temp_dir``)
  and the trajectory format settings of ``[input]`` (not ``chunk_points``: it bounds memory, not
  results). The spilled points themselves (24 bytes a point) stay in ``[slicing] temp_dir``, not
  in the output folder, and are deleted whenever kinreg ends (finished, error, Ctrl-C); only a
  *killed* run (SIGKILL, SIGTERM, power cut) leaves them, and ``--resume`` then re-uses them
  (``--overwrite`` deletes them). Points are needed again only to detect planes of scans not in
  the cache and to write ``sequence.e57``; without a kept spill that costs one more pass over
  the cloud.
- ``planes``: one entry per scan (a kill during plane detection keeps the finished scans),
  keyed by the slice key, the scan's index and ``[planes]``; ``static-planes`` likewise per
  static scan, keyed by the static E57 file.
- ``link``: all pairwise links, keyed by the stations and planes themselves (so also by what
  moved them, e.g. ``[initial_transform]`` of the reference planes), ``[matching]``, ``[drift]``,
  ``[pairwise]`` and (with static scans) ``[static]``.
- The block adjustment is not stored: it takes seconds, and its result is what the outputs
  are keyed by.
- ``output``: which ``corrected.laz`` and ``sequence.e57`` are in the folder (size and
  modification time), keyed by what they are made of (the cloud, the trajectory and the
  correction; the slice key and the adjusted poses). One that is still current is kept, not
  written again; every other output is always rewritten.

Several runs in one project (:mod:`kinreg.run.runs`) need no other keys: slicing and planes are keyed
by each run's own files, the corrected cloud of each run by its own name and correction, and
``sequence.e57`` by the slicing keys of all runs. Each run keeps its own spill record
(:func:`spill_record_name`), so that the spills of all runs live side by side.

Every key also covers the cache schema and kinreg version. At the end of a finished run the
entries it did not use are deleted, so the cache holds one run's results (kilobytes per scan).

One writer per folder (:func:`open_output_folder`): a run holds an OS lock (``flock``) on
``<out>/.kinreg.lock``, with its pid inside, from before it looks at the folder until it ends; a
second run on the same folder is refused ("another kinreg (pid N) is writing here") and changes
nothing. The kernel releases the lock of a process that ends in any way, so a killed run never
leaves a lock that blocks: its file is taken over. The lock lives beside the cache, not in it,
because ``--overwrite`` deletes the cache folder and a run that stored nothing removes it.

No finished-looking outputs of an unfinished run: a run writes its outputs into
``<out>/.kinreg-staging/`` and moves them into the folder together at the end
(:meth:`RunCache.commit_outputs`), after it has written down what it is going to move and
remove (``.kinreg-staging/.commit.json``): a run killed while moving is completed by the next
one that opens the folder. ``report.json``, the mark of a finished run, goes first (the earlier
one) and comes last (the new one). The outputs of an earlier run stay until then: a failed or
killed ``--resume`` leaves them as they were, beside only the cache and hidden temporaries; a
still-current large output of the earlier run is kept as it is, the others are replaced or
removed.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import json
import logging
import os
import re
import shutil
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from kinreg.config import KinregConfig
from kinreg.errors import ConfigError, InputError, OutputError
from kinreg.geometry import Pose
from kinreg.io.checks import time_filter
from kinreg.io.cloud import open_cloud
from kinreg.progress import Progress
from kinreg.run import runs
from kinreg.run.codecs import planes_to_arrays, stations_to_arrays
from kinreg.run.spill import (
    RECORDS_FILE,
    SPILL_COMPLETE,
    SPILL_PREFIX,
    QuasiStaticSequence,
    adopt_records,
    make_spill_folder,
    slice_quasi_static,
    summary_from_arrays,
)
from kinreg.run.stage_cache import CacheEntry, StageCache, process_alive
from kinreg.types import Plane, SlicingSummary, Trajectory

try:
    import fcntl
except ImportError:  # pragma: no cover  (Windows: no lock)
    fcntl = None  # type: ignore[assignment]

log = logging.getLogger(__name__)

CACHE_FOLDER = ".kinreg-cache"
LOCK_FILE = ".kinreg.lock"
STAGING_FOLDER = ".kinreg-staging"
# In the staging folder while its outputs are moved into place: what is moved and what removed.
_COMMIT_RECORD = ".commit.json"
# Written first and moved last: its presence marks a finished run.
_FINISHED_MARK = "report.json"
# Where the spill of the run is while it lives (a JSON file in the cache folder); with several
# runs, each has its own: spill.json for the first, spill_r2.json for the second, ...
_SPILL_RECORD = "spill.json"
_SPILL_FILE = re.compile(rf"unit_\d+\.bin|{re.escape(RECORDS_FILE)}(\.part)?")


@dataclass
class StageUse:
    """How many items of a stage came from the cache and how many were computed."""

    reused: int = 0
    computed: int = 0


@dataclass
class RunCache:
    """The stage cache of one run in its output folder: what it used and what it reused."""

    out_dir: Path
    cache: StageCache
    # every output name this run may find or leave in the folder (runs.output_files)
    outputs: tuple[str, ...] = ()
    used: set[tuple[str, str]] = field(default_factory=set)
    use: dict[str, StageUse] = field(default_factory=dict)

    def key(self, stage: str, *parts: Any) -> str:
        key = self.cache.key(stage, *parts)
        self.used.add((stage, key))
        return key

    def load(self, stage: str, key: str) -> CacheEntry | None:
        return self.cache.load(stage, key)

    def store(self, stage: str, key: str, arrays: Mapping[str, np.ndarray],
              meta: Mapping[str, Any] | None = None) -> None:
        self.cache.store(stage, key, arrays, meta)

    def count(self, stage: str, reused: int = 0, computed: int = 0) -> None:
        use = self.use.setdefault(stage, StageUse())
        use.reused += reused
        use.computed += computed

    def summary(self) -> dict[str, dict[str, int]]:
        """Per stage: ``{"reused": n, "computed": m}`` (for the report)."""
        return {stage: {"reused": u.reused, "computed": u.computed} for stage, u in self.use.items()}

    # ------------------------------------------------------------------ outputs

    def output_is_current(self, name: str, key: str) -> bool:
        """Whether ``out_dir/name`` is the file recorded under ``key`` (same size and
        modification time as when this kinreg wrote it)."""
        entry = self.load("output", key)
        path = self.out_dir / name
        if entry is None or not path.is_file():
            return False
        st = path.stat()
        return entry.meta.get("file") == name and entry.meta.get("size") == st.st_size and \
            entry.meta.get("mtime_ns") == st.st_mtime_ns

    def record_output(self, name: str, key: str) -> None:
        """Record ``name``, just written into the staging folder, under ``key`` (moving it into
        the output folder keeps its size and modification time)."""
        st = (self.staging / name).stat()
        self.store("output", key, {}, {"file": name, "size": st.st_size, "mtime_ns": st.st_mtime_ns})

    @property
    def staging(self) -> Path:
        """Where this run writes its outputs (:meth:`start_outputs`) until :meth:`commit_outputs`."""
        return self.out_dir / STAGING_FOLDER

    def start_outputs(self) -> Path:
        """Create the staging folder (if need be) and return it."""
        try:
            self.staging.mkdir(exist_ok=True)
        except OSError as e:
            raise OutputError(f"cannot create a folder: {e.strerror or e}", self.staging) from None
        return self.staging

    def commit_outputs(self, keep: frozenset[str] = frozenset()) -> None:
        """Move every output written into the staging folder into the output folder, and remove
        every other output of an earlier run except those in ``keep`` (still current). Written
        down first, so that a run killed halfway is completed by the next (see the module
        docstring). Raises :class:`OutputError`."""
        written = [name for name in self.outputs if (self.staging / name).is_file()]
        gone = [name for name in self.outputs
                if name not in written and name not in keep and (self.out_dir / name).exists()]
        try:
            self.start_outputs()
            record = self.staging / _COMMIT_RECORD
            tmp = record.with_name(f"{record.name}.tmp-{os.getpid()}")
            tmp.write_text(json.dumps({"move": written, "remove": gone}) + "\n", encoding="utf-8")
            os.replace(tmp, record)
        except OSError as e:
            raise _output_error(e, self.staging) from None
        _apply_commit(self.out_dir, written, gone)

    def discard_outputs(self) -> None:
        """Delete the staging folder of an unfinished run, unless its outputs are being moved
        into place (a commit record): then the next run completes that."""
        if self.staging.is_dir() and not (self.staging / _COMMIT_RECORD).exists():
            shutil.rmtree(self.staging, ignore_errors=True)

    def finish(self) -> None:
        """After a finished run: delete the entries it did not use."""
        n = self.cache.prune(self.used)
        if n:
            log.info("stage cache: %d entries of earlier runs deleted", n)


# --------------------------------------------------------------------------- the output folder


def output_folder_state(out_dir: Path, output_files: tuple[str, ...]) -> tuple[bool, bool]:
    """(holds kinreg results, holds a stage cache)."""
    results = out_dir.is_dir() and any((out_dir / name).exists() for name in output_files)
    return results, (out_dir / CACHE_FOLDER).is_dir()


@contextmanager
def open_output_folder(out_dir: Path, fixed_outputs: tuple[str, ...], n_runs: int, overwrite: bool,
                       resume: bool) -> Iterator[RunCache]:
    """Open the output folder for one ``kinreg process`` run of ``n_runs`` runs: take its writer
    lock (:func:`output_folder_lock`), complete the commit of a run killed while moving its
    outputs into place, then check the folder against the flags and open the stage cache
    (:func:`open_run_cache`). The lock is held until the block ends; on leaving it without a
    commit, the staged outputs are deleted. Raises :class:`OutputError` (another kinreg writes
    here, ...) and :class:`ConfigError` (both flags), before anything in the folder changes."""
    if overwrite and resume:
        raise ConfigError("--resume and --overwrite exclude each other (--resume re-uses the stage cache, "
                          "--overwrite starts afresh)")
    with output_folder_lock(out_dir):
        complete_commit(out_dir, fixed_outputs)
        outputs = runs.output_files(out_dir, fixed_outputs, n_runs)
        run = open_run_cache(out_dir, outputs, overwrite=overwrite, resume=resume)
        try:
            yield run
        except OutputError as e:
            if e.path is None or Path(e.path).parent != run.staging:
                raise
            raise OutputError(e.reason, out_dir / Path(e.path).name) from None  # the name the user knows
        finally:
            run.discard_outputs()


@contextmanager
def output_folder_lock(out_dir: Path) -> Iterator[None]:
    """Hold the writer lock of ``out_dir`` (created if missing) while the block runs: an
    exclusive ``flock`` on ``out_dir/.kinreg.lock``, which holds this process's pid. Raises
    :class:`OutputError` "another kinreg (pid N) is writing here" at once if another process
    (or another open of this process) holds it. A lock file left by a killed process holds no
    lock and is taken over. Without ``fcntl`` (Windows) there is no lock."""
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputError("exists and is not a folder", out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"cannot create the folder: {e.strerror or e}", out_dir) from None
    if fcntl is None:  # pragma: no cover
        yield
        return
    path = out_dir / LOCK_FILE
    fd = _take_lock(path, out_dir)
    try:
        try:
            earlier = os.pread(fd, 64, 0).decode("ascii", "replace").strip()
            if earlier:
                log.info("%s: taken over from pid %s, which is no longer running", path, earlier)
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
        except OSError as e:
            raise OutputError(f"cannot write: {e.strerror or e}", path) from None
        yield
    finally:
        # Unlinked while still held: a process that opened this file meanwhile finds, once it
        # holds the lock, that its file is no longer the one at the path, and starts over.
        path.unlink(missing_ok=True)
        os.close(fd)


def _take_lock(path: Path, out_dir: Path) -> int:
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as e:
            raise OutputError(f"cannot create the lock file: {e.strerror or e}", path) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            if e.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                # A file system without locks (some network shares) must not stop the work.
                log.warning("%s: cannot lock (%s); make sure that no other kinreg writes here",
                            path, e.strerror or e)
                return fd
            holder = _lock_holder(fd)
            os.close(fd)
            raise OutputError(f"another kinreg (pid {holder}) is writing here", out_dir) from None
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)  # the holder removed it before we got it: take the new one


def _lock_holder(fd: int) -> str:
    """The pid in a held lock file. The holder writes it just after taking the lock, over the
    pid of a killed holder, if any: wait a moment for a living one."""
    text = ""
    for _ in range(50):
        text = os.pread(fd, 64, 0).decode("ascii", "replace").strip()
        if text.isdigit() and process_alive(int(text)):
            return text
        time.sleep(0.01)
    return text if text.isdigit() else "unknown"


def complete_commit(out_dir: Path, fixed_outputs: tuple[str, ...]) -> None:
    """Complete the commit of a run killed while it moved its outputs into place, and delete
    the staging folder of a run killed before that. Only under the writer lock."""
    staging = out_dir / STAGING_FOLDER
    if not staging.is_dir() or staging.is_symlink():
        return
    try:
        data = json.loads((staging / _COMMIT_RECORD).read_text(encoding="utf-8"))
        move, remove = list(data["move"]), list(data["remove"])
    except (OSError, ValueError, KeyError, TypeError):  # no record: the run was killed before its end
        move = remove = []
    # The record is a file in the user's folder: act on output names only.
    names = set(fixed_outputs)
    if (move or remove) and all(_is_output_name(n, names) for n in move + remove):
        log.info("%s: completing the commit of an interrupted run", out_dir)
        _apply_commit(out_dir, [n for n in move if (staging / n).is_file()], remove)
    shutil.rmtree(staging, ignore_errors=True)


def _is_output_name(name: object, names: set[str]) -> bool:
    return isinstance(name, str) and (name in names or _RUN_OUTPUT_NAME.fullmatch(name) is not None)


_RUN_OUTPUT_NAME = re.compile(r"corrected_r\d+\.laz|trajectory_corrected_r\d+\.txt")


def _apply_commit(out_dir: Path, move: Sequence[str], remove: Sequence[str]) -> None:
    """Move ``move`` from the staging folder into ``out_dir`` and delete ``remove`` there: the
    finished mark of the earlier run first, the new one last; then the staging folder goes."""
    staging = out_dir / STAGING_FOLDER
    last = [name for name in move if name == _FINISHED_MARK]
    try:
        (out_dir / _FINISHED_MARK).unlink(missing_ok=True)
        for name in remove:
            (out_dir / name).unlink(missing_ok=True)
        for name in [*(name for name in move if name != _FINISHED_MARK), *last]:
            os.replace(staging / name, out_dir / name)
        (staging / _COMMIT_RECORD).unlink(missing_ok=True)
    except OSError as e:
        raise OutputError(f"cannot move the outputs into place ({e.strerror or e}); the next kinreg process "
                          "--resume in this folder completes it", out_dir) from None
    shutil.rmtree(staging, ignore_errors=True)


def _output_error(e: OSError, path: Path) -> OutputError:
    if e.errno == errno.ENOSPC:
        return OutputError("disk full while writing", path)
    return OutputError(f"cannot write: {e.strerror or e}", path)


def open_run_cache(out_dir: Path, output_files: tuple[str, ...], overwrite: bool, resume: bool) -> RunCache:
    """Check the output folder against the flags and open its stage cache (under the writer
    lock: :func:`open_output_folder`).

    - neither flag: the folder must hold no kinreg results and no stage cache;
    - ``resume``: the folder's cache is used; a folder that holds neither results nor a cache
      but other files is refused (a wrong ``--out``), a missing or empty one starts afresh;
    - ``overwrite``: the cache (and a kept spill) is deleted, the run starts afresh.

    Stale temporary files of killed runs are removed. Raises :class:`OutputError` or
    :class:`ConfigError` (both flags).
    """
    if overwrite and resume:
        raise ConfigError("--resume and --overwrite exclude each other (--resume re-uses the stage cache, "
                          "--overwrite starts afresh)")
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputError("exists and is not a folder", out_dir)
    has_results, has_cache = output_folder_state(out_dir, output_files)
    if not overwrite and not resume:
        if has_results:
            raise OutputError("already holds kinreg results; use --overwrite to replace them or --resume to "
                              "update them", out_dir)
        if has_cache:
            raise OutputError("holds an unfinished kinreg run; use --resume to continue it or --overwrite to "
                              "start afresh", out_dir)
    if resume and not has_results and not has_cache and out_dir.is_dir() and \
            any(p.name not in (LOCK_FILE, STAGING_FOLDER) for p in out_dir.iterdir()):
        raise OutputError("holds no kinreg run to resume (no results, no .kinreg-cache); check --out or "
                          "leave out --resume", out_dir)
    cache = StageCache(out_dir / CACHE_FOLDER)
    if overwrite and has_cache:
        for record in sorted(cache.folder.glob("spill*.json")):
            _remove_recorded_spill(cache.folder, record.name)
        try:
            if cache.folder.exists():  # removing the last record removes an otherwise empty cache folder
                shutil.rmtree(cache.folder)
        except OSError as e:
            raise OutputError(f"cannot delete the stage cache: {e.strerror or e}", cache.folder) from None
    if resume and has_cache:
        log.info("%s: resuming with the stage cache", out_dir)
    cache.remove_stale()
    remove_stale_outputs(out_dir, output_files)
    return RunCache(out_dir, cache, output_files)


def remove_stale_outputs(out_dir: Path, output_files: tuple[str, ...]) -> None:
    """Delete the temporary files of outputs (``.NAME.tmp-PID...``) left by killed runs."""
    if not out_dir.is_dir():
        return
    stems = {Path(name).stem for name in output_files} | set(output_files)
    pattern = re.compile(r"\.(.+)\.tmp-(\d+)(\.[A-Za-z0-9]+)?")
    for path in out_dir.iterdir():
        m = pattern.fullmatch(path.name)
        if m and m.group(1) in stems and path.is_file() and not process_alive(int(m.group(2))):
            path.unlink(missing_ok=True)


# --------------------------------------------------------------------------- slicing and its spill


def spill_record_name(run_index: int) -> str:
    """The name of the spill record of the run ``run_index`` (0-based) in the cache folder."""
    return _SPILL_RECORD if run_index == 0 else f"spill_r{run_index + 1}.json"


def _read_spill_record(cache_folder: Path, name: str = _SPILL_RECORD) -> tuple[str, Path] | None:
    try:
        data = json.loads((cache_folder / name).read_text(encoding="utf-8"))
        return str(data["key"]), Path(data["folder"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _write_spill_record(cache_folder: Path, key: str, folder: Path, name: str = _SPILL_RECORD) -> None:
    cache_folder.mkdir(parents=True, exist_ok=True)
    path = cache_folder / name
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps({"key": key, "folder": str(folder.resolve())}) + "\n", encoding="utf-8")
    os.replace(tmp, path)


def _remove_spill(folder: Path) -> None:
    """Delete a spill folder, but only one that looks like a spill: the path comes from a file in
    the user's folder, and a spill holds nothing but unit files, the cloud's decoded copy and its
    completion mark."""
    if not folder.is_dir() or folder.is_symlink() or not folder.name.startswith(SPILL_PREFIX):
        return
    if all(_SPILL_FILE.fullmatch(p.name) or p.name == SPILL_COMPLETE for p in folder.iterdir()):
        shutil.rmtree(folder, ignore_errors=True)
    else:
        log.warning("%s: not deleted: it holds files that are not kinreg's spill", folder)


def _remove_recorded_spill(cache_folder: Path, name: str = _SPILL_RECORD) -> None:
    record = _read_spill_record(cache_folder, name)
    if record is not None:
        _remove_spill(record[1])
    (cache_folder / name).unlink(missing_ok=True)
    with contextlib.suppress(OSError):
        cache_folder.rmdir()  # a run that stored nothing (it failed in slicing) leaves no cache


class CachedSlices:
    """The sliced run: its index (from the cache or from slicing now) and, on demand, its
    points (a kept spill reopened, or the cloud sliced again)."""

    def __init__(self, run: RunCache, key: str, cloud_path: Path, index: Mapping[str, np.ndarray],
                 n_points_input: int, sequence: QuasiStaticSequence | None,
                 slice_again: Callable[[], QuasiStaticSequence], record: str = _SPILL_RECORD) -> None:
        self.run = run
        self.key = key
        self.record = record  # the name of this run's spill record in the cache folder
        self.cloud_path = cloud_path
        self.index = index
        self.n_points_input = n_points_input
        self.summary: SlicingSummary = summary_from_arrays(index)
        self._sequence = sequence
        self._slice_again = slice_again

    def __len__(self) -> int:
        return len(self.index["scan_id"])

    def _kept(self) -> QuasiStaticSequence | None:
        """The open sequence or the kept spill of an interrupted run, if any."""
        if self._sequence is None:
            record = _read_spill_record(self.run.cache.folder, self.record)
            if record is not None and record[0] == self.key:
                self._sequence = QuasiStaticSequence.reopen(record[1], self.index)
                if self._sequence is not None:
                    log.info("slice: the points of an interrupted run are re-used from %s", record[1])
        return self._sequence

    def records(self) -> Path | None:
        """The cloud's decoded point records, where the open or kept spill holds them (never
        slices again for them)."""
        kept = self._kept()
        return None if kept is None else kept.records

    def sequence(self) -> QuasiStaticSequence:
        """The sequence with its points: the open one, the kept spill of an interrupted run, or
        the cloud sliced again (one pass; the result must equal the cached index)."""
        kept = self._kept()
        if kept is not None:
            return kept
        sequence = self._slice_again()  # deletes an incomplete spill first
        if not _same_index(sequence.index_arrays(), self.index):
            raise InputError("changed since its scans were cached, though its size and modification time did "
                             "not; use --overwrite to start afresh", self.cloud_path)
        self._sequence = sequence
        return sequence

    def close(self) -> None:
        """Delete the spill and its record."""
        _remove_recorded_spill(self.run.cache.folder, self.record)


def _same_index(a: Mapping[str, np.ndarray], b: Mapping[str, np.ndarray]) -> bool:
    return set(a) == set(b) and all(np.array_equal(np.asarray(a[k]), np.asarray(b[k])) for k in a)


@contextmanager
def sliced_run(run: RunCache, trajectory_path: Path, cloud_path: Path, trajectory: Trajectory,
               config: KinregConfig, progress: Progress, run_index: int = 0,
               decoded: Path | None = None) -> Iterator[CachedSlices]:
    """The ``slice`` stage through the cache (see the module docstring). On leaving, also by an
    exception or Ctrl-C, the spill is deleted; only a killed process (SIGKILL, SIGTERM, power cut)
    leaves it, and then ``--resume`` (or ``--overwrite``) of the same folder finds it. Each of
    several runs (``run_index``, 0-based) keeps its own spill record, so that their spills live
    side by side; the cache entries need nothing more: they are keyed by the run's files.
    ``decoded``: the cloud's points as an earlier slicing decoded them, read instead of decoding
    the cloud where the file is still there."""
    name = spill_record_name(run_index)
    input_part = {"trajectory_format": config.input.trajectory_format,
                  "trajectory_columns": config.input.trajectory_columns,
                  "cloud_time_offset_s": config.input.cloud_time_offset_s}
    # where the spill goes, and whether it keeps the decoded points, is no result
    slicing_part = dataclasses.replace(config.slicing, temp_dir="", keep_decoded=True)
    key = run.key("slice", trajectory_path, cloud_path, slicing_part, input_part)
    entry = run.load("slice", key)
    # the earlier slicing's decoded copy, linked into the new spill before the earlier spill goes
    fresh = make_spill_folder(config.slicing) if entry is None and decoded is not None else None
    copy = adopt_records(decoded, fresh) if fresh is not None else None

    def slice_now(folder: Path | None = None, copy: Path | None = None) -> QuasiStaticSequence:
        folder = folder or make_spill_folder(config.slicing)
        try:
            _remove_recorded_spill(run.cache.folder, name)
            try:
                _write_spill_record(run.cache.folder, key, folder, name)
            except OSError as e:
                raise OutputError(f"cannot write the stage cache: {e.strerror or e}", run.cache.folder) from None
            with open_cloud(cloud_path, times=time_filter(config.input), decoded=copy) as cloud:
                sequence = slice_quasi_static(trajectory, cloud, config.slicing, config.input.chunk_points,
                                              progress=progress, folder=folder,
                                              keep_records=config.slicing.keep_decoded)
        except BaseException:
            shutil.rmtree(folder, ignore_errors=True)
            _remove_recorded_spill(run.cache.folder, name)
            raise
        run.count("slice", computed=1)
        return sequence

    sequence = None
    try:
        record = _read_spill_record(run.cache.folder, name)
        if record is not None and (entry is None or record[0] != key):
            _remove_recorded_spill(run.cache.folder, name)  # an unfinished spill, or one of other inputs
        if entry is None:
            with open_cloud(cloud_path) as cloud:
                n_points_input = cloud.info.n_points
            sequence = slice_now(fresh, copy)
    except BaseException:
        if fresh is not None:
            shutil.rmtree(fresh, ignore_errors=True)
        raise
    if sequence is not None:
        index = sequence.index_arrays()
        run.store("slice", key, index, {"n_points_input": n_points_input})
    else:
        assert entry is not None
        index, n_points_input = entry.arrays, int(entry.meta["n_points_input"])
        run.count("slice", reused=1)
        log.info("slice: %d scans re-used from the stage cache", len(index["scan_id"]))
    slices = CachedSlices(run, key, cloud_path, index, n_points_input, sequence, slice_now, name)
    try:
        yield slices
    finally:
        slices.close()


# --------------------------------------------------------------------------- stage results as arrays


def content_parts(stations: Sequence[Any], planes: Sequence[tuple[Plane, ...]]) -> list[Any]:
    """Key parts that stand for the stations and planes themselves (their arrays, by name)."""
    arrays = {**{f"station.{k}": v for k, v in stations_to_arrays(stations).items()},
              **{f"planes.{k}": v for k, v in planes_to_arrays(planes).items()}}
    return [part for name in sorted(arrays) for part in (name, arrays[name])]


def dataclass_parts(obj: Any) -> list[Any]:
    """Key parts that stand for a dataclass of arrays, poses and plain values (e.g. a drift
    correction with its trajectory), field by field, so that a field added later is covered."""
    parts: list[Any] = [type(obj).__qualname__]
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        parts.append(f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, (type, Pose)):
            parts.extend(dataclass_parts(value))
        else:
            parts.append(value)
    return parts
