"""Writing the quasi-static sequence as one ASTM E57 file (conventions: :mod:`kinreg.io.e57`).

:class:`E57SequenceWriter` stores one ``data3D`` entry per scan, points in the scan frame as
double-precision ``Float`` (8 bytes per coordinate, exact round trip; a 0.01 mm ``ScaledInteger``
would save about 60 % of the file but lose the exactness for no gain at the sizes kinreg writes),
``intensity`` as single ``Float``, ``timeStamp`` as double ``Float``. kinreg specific values (the
scan id, kind, centre time and point count) live in the ``kinreg`` extension namespace so the
file stays a conforming E57 file. Bump :data:`~kinreg.io.e57.E57_SCHEMA_VERSION` when any of that
changes meaning.
"""

from __future__ import annotations

import logging
import os
import uuid
from collections.abc import Iterable, Sized
from contextlib import suppress
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pye57 import libe57

from kinreg import __version__
from kinreg.errors import OutputError
from kinreg.geometry import FloatArray
from kinreg.io.e57 import _CARTESIAN, _E57_FAILURES, E57_SCHEMA_VERSION, KINREG_E57_PREFIX, KINREG_E57_URI, _reason
from kinreg.progress import NullProgress, Progress
from kinreg.types import Scan

logger = logging.getLogger(__name__)


#: Points per write block: 1 M points cost 36 MB of buffers, independent of the scan size.
WRITE_BLOCK_POINTS = 1_000_000


def _guid(*parts: object) -> str:
    """A deterministic ``{uuid}`` from names, so that rerunning gives an identical file."""
    name = ":".join(["kinreg", *map(str, parts)])
    return f"{{{uuid.uuid5(uuid.NAMESPACE_URL, name)}}}"


class E57SequenceWriter:
    """Writes scans, one ``data3D`` entry each, into a new E57 file; atomic.

    The file is written under a temporary name in the target folder and renamed on a
    successful :meth:`close`; if anything fails (or the ``with`` block raises) the temporary
    file is removed and nothing is left behind. Every entry holds: ``name``, a deterministic
    ``guid`` (file name + scan id), ``pose`` (= ``scan.T_obj_scan``), ``acquisitionStart``/
    ``acquisitionEnd`` (the scan's window, or its point times' range), ``cartesianBounds``
    (scan frame), ``intensityLimits``, and ``points`` with ``cartesianX/Y/Z`` (double,
    scan frame), ``intensity`` (single) and ``timeStamp`` (double, relative to
    ``acquisitionStart``) where the scan has them.

    Raises :class:`OutputError` if the target exists and ``overwrite`` is off ("exists; use
    --overwrite"), the folder is missing or not writable, or writing fails.
    """

    def __init__(self, path: str | Path, overwrite: bool = False, coordinate_metadata: str = "") -> None:
        self.path = Path(path)
        self.coordinate_metadata = coordinate_metadata  # the CRS (WKT) of the object frame; "" if unknown
        if self.path.is_dir():
            raise OutputError("is a folder; expected an .e57 file name", self.path)
        if self.path.exists() and not overwrite:
            raise OutputError("exists; use --overwrite", self.path)
        folder = self.path.parent
        if not folder.is_dir():
            raise OutputError("folder does not exist", folder)
        self.tmp_path = folder / f".{self.path.name}.tmp-{os.getpid()}"
        self.n_scans = 0
        self._blocks: dict[str, NDArray[Any]] = {}
        self._imf: Any = None
        try:
            self._imf = libe57.ImageFile(str(self.tmp_path), "w")
            self._write_root()
        except _E57_FAILURES as exc:
            self.abort()
            raise OutputError(f"cannot create E57 file: {_reason(exc)}", self.path) from exc

    def _write_root(self) -> None:
        imf = self._imf
        imf.extensionsAdd("", libe57.E57_V1_0_URI)
        imf.extensionsAdd(KINREG_E57_PREFIX, KINREG_E57_URI)
        root = imf.root()
        root.set("formatName", libe57.StringNode(imf, "ASTM E57 3D Imaging Data File"))
        root.set("guid", libe57.StringNode(imf, _guid(self.path.name)))
        root.set("versionMajor", libe57.IntegerNode(imf, libe57.E57_FORMAT_MAJOR))
        root.set("versionMinor", libe57.IntegerNode(imf, libe57.E57_FORMAT_MINOR))
        library = f"kinreg {__version__} / {libe57.E57_LIBRARY_ID}"
        root.set("e57LibraryVersion", libe57.StringNode(imf, library))
        # No creationDateTime: it is optional, and leaving out the wall clock keeps reruns identical.
        root.set("coordinateMetadata", libe57.StringNode(imf, self.coordinate_metadata))
        root.set(f"{KINREG_E57_PREFIX}:schemaVersion", libe57.IntegerNode(imf, E57_SCHEMA_VERSION))
        self._data3d = libe57.VectorNode(imf, True)
        root.set("data3D", self._data3d)
        root.set("images2D", libe57.VectorNode(imf, True))

    @property
    def is_open(self) -> bool:
        return self._imf is not None

    def add_scan(self, scan: Scan) -> None:
        """Append one scan (points in its own frame, pose ``T_obj_scan``) as a ``data3D`` entry.

        Raises :class:`OutputError` for non-finite or mis-shaped values or a write failure;
        the writer is then aborted (temporary file removed) and cannot be used further.
        """
        if self._imf is None:
            raise OutputError("the E57 writer is closed", self.path)
        try:
            self._add_scan(scan)
        except _E57_FAILURES as exc:
            self.abort()
            raise OutputError(f"cannot write scan '{scan.name}': {_reason(exc)}", self.path) from exc
        except BaseException:
            self.abort()
            raise
        self.n_scans += 1

    def _validate(self, scan: Scan) -> tuple[FloatArray, FloatArray | None, NDArray[np.float32] | None]:
        xyz = np.asarray(scan.points_xyz, dtype=np.float64)
        n = len(xyz)
        label = f"scan {scan.scan_id} ('{scan.name}')"
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise OutputError(f"{label}: points_xyz must be (n, 3), got {xyz.shape}", self.path)
        if not np.isfinite(xyz).all():
            bad = int((~np.isfinite(xyz).all(axis=1)).sum())
            raise OutputError(f"{label}: {bad} points with non-finite coordinates", self.path)
        stamps = None if scan.stamps_s is None else np.asarray(scan.stamps_s, dtype=np.float64)
        intensity = None if scan.intensity is None else np.asarray(scan.intensity, dtype=np.float32)
        for name, values in (("stamps_s", stamps), ("intensity", intensity)):
            if values is None:
                continue
            if values.shape != (n,):
                raise OutputError(f"{label}: {name} must be ({n},), got {values.shape}", self.path)
            if not np.isfinite(values).all():
                raise OutputError(f"{label}: {name} has non-finite values", self.path)
        pose = scan.T_obj_scan
        if pose.shape != () or not (np.isfinite(pose.quat_wxyz).all() and np.isfinite(pose.t_xyz).all()):
            raise OutputError(f"{label}: T_obj_scan must be one finite pose", self.path)
        return xyz, stamps, intensity

    def _add_scan(self, scan: Scan) -> None:
        xyz, stamps, intensity = self._validate(scan)
        n = len(xyz)
        imf = self._imf
        node = libe57.StructureNode(imf)
        node.set("guid", libe57.StringNode(imf, _guid(self.path.name, "scan", scan.scan_id)))
        node.set("name", libe57.StringNode(imf, scan.name))
        node.set("description", libe57.StringNode(imf, f"kinreg {scan.kind.value} scan"))
        node.set(f"{KINREG_E57_PREFIX}:scanId", libe57.IntegerNode(imf, int(scan.scan_id)))
        node.set(f"{KINREG_E57_PREFIX}:scanKind", libe57.StringNode(imf, scan.kind.value))
        node.set(f"{KINREG_E57_PREFIX}:pointsSize", libe57.IntegerNode(imf, n))
        if np.isfinite(scan.t_s):
            node.set(f"{KINREG_E57_PREFIX}:scanTime", libe57.FloatNode(imf, float(scan.t_s)))

        pose = libe57.StructureNode(imf)
        rotation = libe57.StructureNode(imf)
        for key, value in zip("wxyz", scan.T_obj_scan.quat_wxyz, strict=True):
            rotation.set(key, libe57.FloatNode(imf, float(value)))
        translation = libe57.StructureNode(imf)
        for key, value in zip("xyz", scan.T_obj_scan.t_xyz, strict=True):
            translation.set(key, libe57.FloatNode(imf, float(value)))
        pose.set("rotation", rotation)
        pose.set("translation", translation)
        node.set("pose", pose)

        # The time origin: the window start where known, else the first point time, so that
        # timeStamp is always relative to an acquisitionStart that exists (E57 standard).
        t_start = scan.t_start_s if np.isfinite(scan.t_start_s) else None
        t_end = scan.t_end_s if np.isfinite(scan.t_end_s) else None
        if stamps is not None and n > 0:
            t_start = float(stamps.min()) if t_start is None else t_start
            t_end = float(stamps.max()) if t_end is None else t_end
        for key, value in (("acquisitionStart", t_start), ("acquisitionEnd", t_end)):
            if value is not None:
                when = libe57.StructureNode(imf)
                when.set("dateTimeValue", libe57.FloatNode(imf, float(value)))
                when.set("isAtomicClockReferenced", libe57.IntegerNode(imf, 0))
                node.set(key, when)

        if n > 0:
            box = libe57.StructureNode(imf)
            # Column by column: numpy's reductions along the first axis of (n, 3) are slow.
            lo = [float(xyz[:, i].min()) for i in range(3)]
            hi = [float(xyz[:, i].max()) for i in range(3)]
            for i, axis in enumerate("xyz"):
                box.set(f"{axis}Minimum", libe57.FloatNode(imf, float(lo[i])))
                box.set(f"{axis}Maximum", libe57.FloatNode(imf, float(hi[i])))
            node.set("cartesianBounds", box)

        prototype = libe57.StructureNode(imf)
        for name in _CARTESIAN:
            prototype.set(name, libe57.FloatNode(imf, 0.0, libe57.E57_DOUBLE))
        if intensity is not None:
            i_min = float(intensity.min()) if n else 0.0
            i_max = float(intensity.max()) if n else 0.0
            prototype.set("intensity", libe57.FloatNode(imf, i_min, libe57.E57_SINGLE, i_min, i_max))
            limits = libe57.StructureNode(imf)
            limits.set("intensityMinimum", libe57.FloatNode(imf, i_min))
            limits.set("intensityMaximum", libe57.FloatNode(imf, i_max))
            node.set("intensityLimits", limits)
        if stamps is not None:
            prototype.set("timeStamp", libe57.FloatNode(imf, 0.0, libe57.E57_DOUBLE))
        points = libe57.CompressedVectorNode(imf, prototype, libe57.VectorNode(imf, True))
        node.set("points", points)
        self._data3d.append(node)

        capacity = max(1, min(WRITE_BLOCK_POINTS, n))
        # name -> (block buffer, source values, offset subtracted block by block)
        columns: dict[str, tuple[NDArray[Any], NDArray[Any], float]] = {
            name: (self._block(name, np.float64, capacity), xyz[:, i], 0.0) for i, name in enumerate(_CARTESIAN)
        }
        if intensity is not None:
            columns["intensity"] = (self._block("intensity", np.float32, capacity), intensity, 0.0)
        if stamps is not None:
            columns["timeStamp"] = (self._block("timeStamp", np.float64, capacity), stamps, t_start or 0.0)
        buffers = libe57.VectorSourceDestBuffer()
        for name, (buffer, _, _) in columns.items():
            buffers.append(libe57.SourceDestBuffer(imf, name, buffer, capacity, True, True))
        # A writer is opened even for an empty scan: without it the entry gets no binary
        # section, which other readers (the Rust e57 crate) reject.
        writer = points.writer(buffers)
        try:
            for start in range(0, n, capacity):
                m = min(capacity, n - start)
                for buffer, values, offset in columns.values():
                    np.subtract(values[start : start + m], offset, out=buffer[:m], casting="same_kind")
                writer.write(m)
        except BaseException:
            # The caller aborts the whole file; a second error from closing would hide the first.
            with suppress(*_E57_FAILURES):
                writer.close()
            raise
        writer.close()

    def _block(self, name: str, dtype: type[np.floating[Any]], capacity: int) -> NDArray[Any]:
        """The write block of column ``name``, ``capacity`` values: one buffer of
        :data:`WRITE_BLOCK_POINTS` kept from scan to scan (a fresh one per scan costs page faults
        and zeroing of every page it fills)."""
        buffer = self._blocks.get(name)
        if buffer is None or len(buffer) < capacity:
            buffer = self._blocks[name] = np.empty(max(WRITE_BLOCK_POINTS, capacity), dtype)
        return buffer[:capacity]

    def close(self) -> None:
        """Finish the file and move it to its final name. Safe to call twice.

        Raises :class:`OutputError` if finishing or renaming fails (nothing is left behind).
        """
        if self._imf is None:
            return
        try:
            self._imf.close()
            self._imf = None
            os.replace(self.tmp_path, self.path)
        except (*_E57_FAILURES, OSError) as exc:
            self.abort()
            reason = _reason(exc) if isinstance(exc, _E57_FAILURES) else (exc.strerror or str(exc))
            raise OutputError(f"cannot finish E57 file: {reason}", self.path) from exc
        logger.info("wrote %s: %d scans", self.path, self.n_scans)

    def abort(self) -> None:
        """Discard the file being written (removes the temporary file). Safe to call twice."""
        imf, self._imf = self._imf, None
        if imf is not None:
            try:
                # cancel() closes the ImageFile and deletes the partial file.
                imf.cancel()
            except _E57_FAILURES as exc:
                logger.debug("cancelling %s failed: %s", self.tmp_path, _reason(exc))
        try:
            self.tmp_path.unlink(missing_ok=True)
        except OSError as exc:
            logger.warning("cannot remove temporary file %s: %s", self.tmp_path, exc)

    def __enter__(self) -> E57SequenceWriter:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_e57_sequence(
    path: str | Path,
    scans: Iterable[Scan],
    overwrite: bool = False,
    progress: Progress | None = None,
    coordinate_metadata: str = "",
) -> int:
    """Write scans (points in their own frames, poses ``T_obj_scan``) as one E57 file;
    ``coordinate_metadata`` (the CRS of the object frame, e.g. its WKT) goes into the root's
    ``coordinateMetadata``.

    ``scans`` is consumed one at a time, so a generator keeps memory at one scan. Returns the
    number of scans written. Atomic: on any failure nothing is left at ``path``. Raises
    :class:`OutputError` (see :class:`E57SequenceWriter`).
    """
    progress = progress or NullProgress()
    progress.start("write E57", total=len(scans) if isinstance(scans, Sized) else None, unit="scans")
    try:
        with E57SequenceWriter(path, overwrite=overwrite, coordinate_metadata=coordinate_metadata) as writer:
            for scan in scans:
                writer.add_scan(scan)
                progress.advance(1)
    finally:
        progress.finish()
    return writer.n_scans
