"""Writing the quasi-static sequence as one ASTM E57 file (conventions: :mod:`kinreg.io.e57`).

:class:`E57SequenceWriter` stores one ``data3D`` entry per scan, points in the scan frame as
double-precision ``Float`` (8 bytes per coordinate, exact round trip; a 0.01 mm ``ScaledInteger``
would save about 60 % of the file but lose the exactness for no gain at the sizes kinreg writes),
``intensity`` as single ``Float``, ``timeStamp`` as double ``Float``. kinreg specific values (the
scan id, kind, centre time and point count) live in the ``kinreg`` extension namespace so the
file stays a conforming E57 file. Bump :data:`~kinreg.io.e57.E57_SCHEMA_VERSION` when any of that
changes meaning.

The file is written here with numpy, not through libE57Format (which writes one 1 KiB page per
``write`` call, with a software CRC each: 5 s of CPU for 20 M points; ``benchmarks/RESULTS.md``).
The layout is libE57Format's (E57 standard, clause 9):

- **Pages.** The file is a sequence of 1024-byte physical pages, each 1020 logical bytes followed
  by the CRC-32C of those bytes, most significant byte first. Logical offset ``l`` lies at physical
  offset ``l // 1020 * 1024 + l % 1020``; the XML names physical offsets.
- **Header.** The first 48 logical bytes: ``ASTM-E57``, version 1.0, the file's physical length,
  the XML section's physical offset and logical length, the page size. It is known only at the
  end: the first page is written again then.
- **Binary sections.** One per scan, right after the header or the previous section: a 32-byte
  section header (``sectionId`` 1, seven reserved bytes, ``sectionLogicalLength``,
  ``dataPhysicalOffset``, ``indexPhysicalOffset`` = 0: no index packet, as libE57Format), then
  data packets: ``packetType`` 1, ``packetFlags`` 0, the packet's logical length - 1 (uint16),
  the bytestream count (uint16), each bytestream's length in this packet (uint16), the
  bytestreams (``cartesianX/Y/Z``, ``intensity``, ``timeStamp`` in the prototype's order, as raw
  little-endian IEEE values), zeros to a multiple of 4 bytes; at most 64 KiB a packet. Every
  packet of a scan holds the same number of records but the last. An empty scan has a section
  header only (``dataPhysicalOffset`` 0).
- **XML.** After the last section, as libE57Format formats it (its number formatting, its
  indentation, ``CDATA`` strings), then zeros to the end of the page.

Points go out in blocks of :data:`WRITE_BLOCK_POINTS` (whole packets), paged into buffers kept from
block to block and written in large pieces past the page cache where the file system takes it
(:class:`kinreg.io.direct_io.DirectWriter`).
"""

from __future__ import annotations

import logging
import os
import struct
import uuid
from collections.abc import Iterable, Sized
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from crc32c import crc32c
from numpy.typing import NDArray

from kinreg._version import __version__
from kinreg.errors import OutputError
from kinreg.geometry import FloatArray
from kinreg.io.direct_io import DirectWriter
from kinreg.io.e57 import _CARTESIAN, _E57_SIGNATURE, E57_SCHEMA_VERSION, KINREG_E57_PREFIX, KINREG_E57_URI
from kinreg.progress import NullProgress, Progress
from kinreg.types import Scan

logger = logging.getLogger(__name__)


#: Points per write block (rounded down to whole packets): 1 M points cost about 80 MB of buffers,
#: independent of the scan size. The file's bytes do not depend on it.
WRITE_BLOCK_POINTS = 1_000_000

PAGE_BYTES = 1024
PAGE_DATA = 1020  # logical bytes a page
PACKET_MAX = 65536  # bytes of one data packet, at most (E57 standard: 2^16)
_SECTION_HEADER = struct.Struct("<B7xQQQ")  # sectionId, reserved, logical length, data and index offsets
_FILE_HEADER = struct.Struct("<8sIIQQQQ")
_E57_URI = "http://www.astm.org/COMMIT/E57/2010-e57-v1.0"
_FLT_MAX = float(np.finfo(np.float32).max)
#: What the root's ``e57LibraryVersion`` names.
LIBRARY_VERSION = f"kinreg {__version__} E57 writer"
#: Bytes of the buffer that paged blocks go through to the file.
FILE_BUFFER_BYTES = 16 << 20


def _guid(*parts: object) -> str:
    """A deterministic ``{uuid}`` from names, so that rerunning gives an identical file."""
    name = ":".join(["kinreg", *map(str, parts)])
    return f"{{{uuid.uuid5(uuid.NAMESPACE_URL, name)}}}"


def physical_offset(logical: int) -> int:
    """The physical file offset of logical offset ``logical``."""
    return logical // PAGE_DATA * PAGE_BYTES + logical % PAGE_DATA


# --------------------------------------------------------------------------- XML, as libE57Format writes it


def _number(value: float, digits: int) -> str:
    """libE57Format's ``floatingPointToStr``: scientific with ``digits`` decimals, trailing zeros
    (and a trailing point) dropped, ``e+00`` dropped."""
    mantissa, exponent = format(value, f".{digits}e").split("e")
    mantissa = mantissa.rstrip("0").removesuffix(".")
    return mantissa if exponent in ("+00", "+000") else f"{mantissa}e{exponent}"


def _float(indent: int, name: str, value: float) -> str:
    """A double ``Float`` node (value left out where 0, libE57Format's default)."""
    if value == 0.0:
        return f'{" " * indent}<{name} type="Float"/>\n'
    return f'{" " * indent}<{name} type="Float">{_number(value, 17)}</{name}>\n'


def _single(indent: int, name: str, value: float, minimum: float, maximum: float) -> str:
    """A single ``Float`` node with its limits (each left out where it is the default)."""
    text = f'{" " * indent}<{name} type="Float" precision="single"'
    if minimum > -_FLT_MAX:
        text += f' minimum="{_number(float(np.float32(minimum)), 7)}"'
    if maximum < _FLT_MAX:
        text += f' maximum="{_number(float(np.float32(maximum)), 7)}"'
    if value == 0.0:
        return text + "/>\n"
    return text + f">{_number(float(np.float32(value)), 7)}</{name}>\n"


def _integer(indent: int, name: str, value: int) -> str:
    if value == 0:
        return f'{" " * indent}<{name} type="Integer"/>\n'
    return f'{" " * indent}<{name} type="Integer">{value}</{name}>\n'


def _string(indent: int, name: str, value: str) -> str:
    """A ``String`` node: its value in ``CDATA``, every ``]]>`` split over two sections."""
    if not value:
        return f'{" " * indent}<{name} type="String"/>\n'
    text = value.replace("]]>", "]]]]><![CDATA[>")
    return f'{" " * indent}<{name} type="String"><![CDATA[{text}]]></{name}>\n'


def _structure(indent: int, name: str, children: Iterable[str]) -> str:
    return f'{" " * indent}<{name} type="Structure">\n{"".join(children)}{" " * indent}</{name}>\n'


def _vector(indent: int, name: str, children: Iterable[str]) -> str:
    return (f'{" " * indent}<{name} type="Vector" allowHeterogeneousChildren="1">\n{"".join(children)}'
            f'{" " * indent}</{name}>\n')


# --------------------------------------------------------------------------- paged file


class _PagedFile:
    """The logical byte stream of an E57 file, cut into CRC'd pages and written in large pieces.

    :meth:`reserve` hands out room for the next logical bytes (after the unpaged rest of the
    previous ones, in a buffer kept from call to call), :meth:`commit` pages and writes whatever
    fills whole pages."""

    def __init__(self, path: Path) -> None:
        self._file = DirectWriter(path, buffer_bytes=FILE_BUFFER_BYTES)
        self.logical_size = 0  # logical bytes committed
        self._logical: NDArray[np.uint8] = np.empty(0, np.uint8)
        self._rest = 0  # committed bytes not yet paged, at the start of _logical
        self._pages: NDArray[np.uint8] = np.empty(0, np.uint8)

    def reserve(self, n: int) -> NDArray[np.uint8]:
        """Room for the next ``n`` logical bytes; valid until :meth:`commit`."""
        need = self._rest + n
        self._grow(need + PAGE_DATA, self._rest)  # room for the padding of the last page too
        return self._logical[self._rest:need]

    def _grow(self, size: int, keep: int) -> None:
        if len(self._logical) < size:
            grown = np.empty(size, np.uint8)
            grown[:keep] = self._logical[:keep]
            self._logical = grown

    def commit(self, n: int, pad: bool = False) -> None:
        """Take the ``n`` bytes filled in after :meth:`reserve`; ``pad``: fill the last page up
        with zeros (the end of the file)."""
        total = self._rest + n
        self.logical_size += n
        if pad and total % PAGE_DATA:
            end = -(-total // PAGE_DATA) * PAGE_DATA
            self._grow(end, total)
            self._logical[total:end] = 0
            total = end
        k = total // PAGE_DATA
        if k:
            self._write_pages(k)
        rest = total - k * PAGE_DATA
        self._logical[:rest] = self._logical[k * PAGE_DATA:total]
        self._rest = rest

    def _write_pages(self, k: int) -> None:
        if len(self._pages) < k * PAGE_BYTES:
            self._pages = np.empty(k * PAGE_BYTES, np.uint8)
        pages = self._pages[:k * PAGE_BYTES].reshape(k, PAGE_BYTES)
        logical = self._logical[:k * PAGE_DATA]
        pages[:, :PAGE_DATA] = logical.reshape(k, PAGE_DATA)
        data = logical.data
        crcs = np.array([crc32c(data[i:i + PAGE_DATA]) for i in range(0, k * PAGE_DATA, PAGE_DATA)], ">u4")
        pages[:, PAGE_DATA:] = crcs.view(np.uint8).reshape(k, 4)
        self._file.write(pages.data)

    @property
    def physical_size(self) -> int:
        return self._file.size

    def close(self, header: bytes) -> None:
        """Write the last page (padded) and ``header`` into the first page; close the file."""
        self.commit(0, pad=True)
        page0 = bytearray(self._file.head[:PAGE_DATA])  # the first page's logical bytes
        page0[:len(header)] = header
        page0 += crc32c(bytes(page0)).to_bytes(4, "big")
        self._file.close(head=page0)

    def abort(self) -> None:
        self._file.__exit__(OSError, None, None)


# --------------------------------------------------------------------------- the writer


@dataclass(frozen=True)
class _Stream:
    """One bytestream of a scan: its values, their type, what is subtracted from them."""

    name: str
    values: NDArray[Any]
    dtype: np.dtype[Any]
    offset: float = 0.0


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
        self._entries: list[str] = []  # each scan's data3D child, XML
        self._lo: list[float] = []  # the scan's bounds (from _validate)
        self._hi: list[float] = []
        self._file: _PagedFile | None = None
        try:
            self._file = _PagedFile(self.tmp_path)
            self._file.reserve(_FILE_HEADER.size)[:] = 0  # written again at the end
            self._file.commit(_FILE_HEADER.size)
        except OSError as exc:
            self.abort()
            raise OutputError(f"cannot create E57 file: {exc.strerror or exc}", self.path) from exc

    def add_scan(self, scan: Scan) -> None:
        """Append one scan (points in its own frame, pose ``T_obj_scan``) as a ``data3D`` entry.

        Raises :class:`OutputError` for non-finite or mis-shaped values or a write failure;
        the writer is then aborted (temporary file removed) and cannot be used further.
        """
        if self._file is None:
            raise OutputError("the E57 writer is closed", self.path)
        try:
            self._add_scan(scan, self._file)
        except OSError as exc:
            self.abort()
            raise OutputError(f"cannot write scan '{scan.name}': {exc.strerror or exc}", self.path) from exc
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
        # Column by column (numpy's reductions along the first axis of (n, 3) are slow); a NaN or an
        # infinity shows in the minimum or the maximum, so these are the finiteness check as well.
        self._lo = [float(xyz[:, i].min()) if n else 0.0 for i in range(3)]
        self._hi = [float(xyz[:, i].max()) if n else 0.0 for i in range(3)]
        if not np.isfinite(self._lo + self._hi).all():
            bad = int((~np.isfinite(xyz).all(axis=1)).sum())
            raise OutputError(f"{label}: {bad} points with non-finite coordinates", self.path)
        stamps = None if scan.stamps_s is None else np.asarray(scan.stamps_s, dtype=np.float64)
        intensity = None if scan.intensity is None else np.asarray(scan.intensity, dtype=np.float32)
        for name, values in (("stamps_s", stamps), ("intensity", intensity)):
            if values is None:
                continue
            if values.shape != (n,):
                raise OutputError(f"{label}: {name} must be ({n},), got {values.shape}", self.path)
            if n and not np.isfinite([values.min(), values.max()]).all():
                raise OutputError(f"{label}: {name} has non-finite values", self.path)
        pose = scan.T_obj_scan
        if pose.shape != () or not (np.isfinite(pose.quat_wxyz).all() and np.isfinite(pose.t_xyz).all()):
            raise OutputError(f"{label}: T_obj_scan must be one finite pose", self.path)
        return xyz, stamps, intensity

    def _add_scan(self, scan: Scan, file: _PagedFile) -> None:
        xyz, stamps, intensity = self._validate(scan)
        n = len(xyz)
        # The time origin: the window start where known, else the first point time, so that
        # timeStamp is always relative to an acquisitionStart that exists (E57 standard).
        t_start = scan.t_start_s if np.isfinite(scan.t_start_s) else None
        t_end = scan.t_end_s if np.isfinite(scan.t_end_s) else None
        if stamps is not None and n > 0:
            t_start = float(stamps.min()) if t_start is None else t_start
            t_end = float(stamps.max()) if t_end is None else t_end

        streams = [_Stream(name, xyz[:, i], np.dtype("<f8")) for i, name in enumerate(_CARTESIAN)]
        i_min = i_max = 0.0
        if intensity is not None:
            i_min = float(intensity.min()) if n else 0.0
            i_max = float(intensity.max()) if n else 0.0
            streams.append(_Stream("intensity", intensity, np.dtype("<f4")))
        if stamps is not None:
            streams.append(_Stream("timeStamp", stamps, np.dtype("<f8"), t_start or 0.0))

        # The binary section: its length is known before its first byte.
        per_packet, packet_bytes = _packet_shape(streams)
        n_full, last = divmod(n, per_packet)
        section_length = _SECTION_HEADER.size + n_full * packet_bytes(per_packet) + (packet_bytes(last) if last else 0)
        section_start = file.logical_size
        data_offset = physical_offset(section_start + _SECTION_HEADER.size) if n else 0
        file.reserve(_SECTION_HEADER.size)[:] = np.frombuffer(
            _SECTION_HEADER.pack(1, section_length, data_offset, 0), np.uint8)
        file.commit(_SECTION_HEADER.size)
        block = max(1, WRITE_BLOCK_POINTS // per_packet) * per_packet
        for start in range(0, n, block):
            _write_packets(file, streams, start, min(block, n - start), per_packet, packet_bytes)
        assert file.logical_size == section_start + section_length

        # The data3D entry, as libE57Format writes it.
        xml = [
            _string(6, "guid", _guid(self.path.name, "scan", scan.scan_id)),
            _string(6, "name", scan.name),
            _string(6, "description", f"kinreg {scan.kind.value} scan"),
            _integer(6, f"{KINREG_E57_PREFIX}:scanId", int(scan.scan_id)),
            _string(6, f"{KINREG_E57_PREFIX}:scanKind", scan.kind.value),
            _integer(6, f"{KINREG_E57_PREFIX}:pointsSize", n),
        ]
        if np.isfinite(scan.t_s):
            xml.append(_float(6, f"{KINREG_E57_PREFIX}:scanTime", float(scan.t_s)))
        quat, t = scan.T_obj_scan.quat_wxyz, scan.T_obj_scan.t_xyz
        xml.append(_structure(6, "pose", [
            _structure(8, "rotation", [_float(10, k, float(v)) for k, v in zip("wxyz", quat, strict=True)]),
            _structure(8, "translation", [_float(10, k, float(v)) for k, v in zip("xyz", t, strict=True)]),
        ]))
        for key, value in (("acquisitionStart", t_start), ("acquisitionEnd", t_end)):
            if value is not None:
                xml.append(_structure(6, key, [_float(8, "dateTimeValue", float(value)),
                                               _integer(8, "isAtomicClockReferenced", 0)]))
        if n > 0:
            lo, hi = self._lo, self._hi
            xml.append(_structure(6, "cartesianBounds", [
                _float(8, f"{axis}{which}", bound[i])
                for i, axis in enumerate("xyz") for which, bound in (("Minimum", lo), ("Maximum", hi))
            ]))
        prototype = [_float(10, name, 0.0) for name in _CARTESIAN]
        if intensity is not None:
            xml.append(_structure(6, "intensityLimits", [_float(8, "intensityMinimum", i_min),
                                                         _float(8, "intensityMaximum", i_max)]))
            prototype.append(_single(10, "intensity", i_min, i_min, i_max))
        if stamps is not None:
            prototype.append(_float(10, "timeStamp", 0.0))
        xml.append(
            f'      <points type="CompressedVector" fileOffset="{physical_offset(section_start)}" recordCount="{n}">\n'
            + _structure(8, "prototype", prototype) + _vector(8, "codecs", []) + "      </points>\n"
        )
        self._entries.append(_structure(4, "vectorChild", xml))

    def _root_xml(self) -> bytes:
        root = [
            _string(2, "formatName", "ASTM E57 3D Imaging Data File"),
            _string(2, "guid", _guid(self.path.name)),
            _integer(2, "versionMajor", 1),
            _integer(2, "versionMinor", 0),
            _string(2, "e57LibraryVersion", LIBRARY_VERSION),
            # No creationDateTime: it is optional, and leaving out the wall clock keeps reruns identical.
            _string(2, "coordinateMetadata", self.coordinate_metadata),
            _integer(2, f"{KINREG_E57_PREFIX}:schemaVersion", E57_SCHEMA_VERSION),
            _vector(2, "data3D", self._entries),
            _vector(2, "images2D", []),
        ]
        text = (
            '<?xml version="1.0" encoding="UTF-8"?>\n'
            '<e57Root type="Structure"\n'
            f'         xmlns="{_E57_URI}"\n'
            f'         xmlns:{KINREG_E57_PREFIX}="{KINREG_E57_URI}">\n'
            + "".join(root) + "</e57Root>\n"
        )
        return text.encode("utf-8")

    def close(self) -> None:
        """Finish the file and move it to its final name. Safe to call twice.

        Raises :class:`OutputError` if finishing or renaming fails (nothing is left behind).
        """
        file = self._file
        if file is None:
            return
        try:
            xml = self._root_xml()
            xml_start = file.logical_size
            file.reserve(len(xml))[:] = np.frombuffer(xml, np.uint8)
            file.commit(len(xml), pad=True)
            header = _FILE_HEADER.pack(_E57_SIGNATURE, 1, 0, file.physical_size, physical_offset(xml_start),
                                       len(xml), PAGE_BYTES)
            self._file = None
            file.close(header)
            os.replace(self.tmp_path, self.path)
        except OSError as exc:
            self._file = file
            self.abort()
            raise OutputError(f"cannot finish E57 file: {exc.strerror or exc}", self.path) from exc
        logger.info("wrote %s: %d scans", self.path, self.n_scans)

    def abort(self) -> None:
        """Discard the file being written (removes the temporary file). Safe to call twice."""
        file, self._file = self._file, None
        if file is not None:
            try:
                file.abort()
            except OSError as exc:
                logger.debug("closing %s failed: %s", self.tmp_path, exc)
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


def _packet_shape(streams: list[_Stream]) -> tuple[int, Any]:
    """Records a full data packet holds, and the packet's bytes for ``m`` records (a function)."""
    header = 6 + 2 * len(streams)
    record = sum(s.dtype.itemsize for s in streams)
    per_packet = (PACKET_MAX - header) // record

    def packet_bytes(m: int) -> int:
        return -(-(header + m * record) // 4) * 4

    return per_packet, packet_bytes


def _write_packets(file: _PagedFile, streams: list[_Stream], start: int, count: int, per_packet: int,
                   packet_bytes: Any) -> None:
    """Records ``start`` to ``start + count`` as data packets of ``per_packet`` records (the last
    one fewer), built into the file's next logical bytes."""
    n_full, last = divmod(count, per_packet)
    full_bytes = n_full * packet_bytes(per_packet)
    out = file.reserve(full_bytes + (packet_bytes(last) if last else 0))
    for first, m, n_packets, area in (
        (start, per_packet, n_full, out[:full_bytes]),
        (start + n_full * per_packet, last, 1 if last else 0, out[full_bytes:]),
    ):
        if not n_packets:
            continue
        length = packet_bytes(m)
        packets = area.reshape(n_packets, length)
        header = struct.pack(f"<BBHH{len(streams)}H", 1, 0, length - 1, len(streams),
                             *(m * s.dtype.itemsize for s in streams))
        packets[:, :len(header)] = np.frombuffer(header, np.uint8)
        at = len(header)
        for s in streams:
            size = m * s.dtype.itemsize
            target = packets[:, at:at + size].view(s.dtype)
            source = s.values[first:first + n_packets * m].reshape(n_packets, m)
            np.subtract(source, s.offset, out=target, casting="same_kind")
            at += size
        packets[:, at:] = 0
    file.commit(len(out))


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
