"""Checks of a LAS/LAZ file's header against the file itself, before laspy or lazrs read it.

laspy trusts the header and lazrs trusts the LAZ chunk table: a damaged count makes them read one
point of thirty thousand, raise ``IndexError`` or ``MemoryError``, or abort the whole process (a
chunk count of 2.5 billion makes lazrs allocate 40 GB, and Rust aborts on a failed allocation,
which no ``except`` can catch). :func:`check_las_file` reads the fixed header, the VLR and EVLR
chains, the LASzip VLR and the chunk table's plain fields with :mod:`struct` and raises
:class:`~kinreg.errors.CloudError` naming the file for anything that does not fit.

Layout (ASPRS LAS 1.4 R15, little endian): the public header block is 227 bytes in 1.0-1.2, 235 in
1.3 and 375 in 1.4; a VLR header is 54 bytes, an EVLR header 60. In LAZ the point data starts with
an 8-byte signed offset of the chunk table (-1: the offset is in the file's last 8 bytes); the
chunk table starts with ``version`` (u32) and ``number_of_chunks`` (u32), followed by the
arithmetic-coded chunk sizes.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from pathlib import Path

import lazrs

from kinreg.errors import CloudError

HEADER_SIZES = {0: 227, 1: 227, 2: 227, 3: 235, 4: 375}
VLR_HEADER_SIZE = 54
EVLR_HEADER_SIZE = 60
# Smallest record of each point format (LAS 1.4 table 7 ff.); extra bytes may follow.
POINT_RECORD_SIZES = {0: 20, 1: 28, 2: 26, 3: 34, 4: 57, 5: 63, 6: 30, 7: 36, 8: 38, 9: 59, 10: 67}
# The LAS version that introduced each point format.
MIN_MINOR_VERSION = {0: 0, 1: 0, 2: 2, 3: 2, 4: 3, 5: 3, 6: 4, 7: 4, 8: 4, 9: 4, 10: 4}
LASZIP_USER_ID = "laszip encoded"
LASZIP_RECORD_ID = 22204
VARIABLE_CHUNK_SIZE = 0xFFFFFFFF
# A coordinate is int32 * scale + offset. Scales outside this range are damage, not resolution
# (real files use 1e-4 .. 1 m); offsets beyond 1e9 m are no place on or near the earth.
MIN_SCALE = 1e-10
MAX_SCALE = 1e3
MAX_ABS_OFFSET = 1e9


@dataclass(frozen=True)
class LasFileFacts:
    """What the checks read: version, point format, record length, point count, compression."""

    version: tuple[int, int]
    point_format: int
    record_length: int
    n_points: int
    compressed: bool
    offset_to_points: int
    n_chunks: int | None = None
    chunk_size: int | None = None


def _first_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return text[0] if text else type(e).__name__


def _fail(reason: str, path: Path) -> CloudError:
    return CloudError(reason, path)


def check_las_file(path: str | Path) -> LasFileFacts:
    """Check the header of the LAS/LAZ file at ``path`` against the file's size and contents.

    Raises :class:`CloudError` naming the file: not a LAS file, an unsupported version, a header
    size, point format or record length that does not fit the version, scales that are not finite
    and in ``[MIN_SCALE, MAX_SCALE]``, offsets that are not finite and below ``MAX_ABS_OFFSET``,
    no points, more or fewer points than the point data holds, VLRs or EVLRs that run past their
    space, a LAZ without LASzip VLR or with a chunk table that does not fit the file.
    """
    p = Path(path)
    try:
        size = p.stat().st_size
        with open(p, "rb") as f:
            return _check(f, size, p)
    except OSError as e:
        raise CloudError(f"cannot read: {e.strerror or e}", p) from None


def _read_at(f, offset: int, n: int, size: int, what: str, p: Path) -> bytes:  # type: ignore[no-untyped-def]
    if offset < 0 or offset + n > size:
        raise _fail(f"{what} at byte {offset:,} lies beyond the end of the file ({size:,} bytes; truncated?)", p)
    f.seek(offset)
    data: bytes = f.read(n)
    if len(data) < n:
        raise _fail(f"{what} at byte {offset:,}: file ends early (truncated?)", p)
    return data


def _check(f, size: int, p: Path) -> LasFileFacts:  # type: ignore[no-untyped-def]
    if size < 4 or _read_at(f, 0, 4, size, "signature", p) != b"LASF":
        raise _fail("cannot open as LAS/LAZ: no 'LASF' signature", p)
    if size < 227:
        raise _fail(f"file of {size} bytes is shorter than a LAS header (227 bytes; truncated?)", p)
    head = _read_at(f, 0, min(size, 375), size, "header", p)
    major, minor = head[24], head[25]
    if major != 1 or minor not in HEADER_SIZES:
        raise _fail(f"LAS version {major}.{minor} is not supported (1.0-1.4)", p)
    header_size, offset_to_points, n_vlrs = struct.unpack_from("<HII", head, 94)
    format_byte, record_length, legacy_count = struct.unpack_from("<BHI", head, 104)
    if header_size < HEADER_SIZES[minor]:
        raise _fail(f"header size {header_size} is smaller than the {HEADER_SIZES[minor]} bytes of LAS 1.{minor}", p)
    if len(head) < HEADER_SIZES[minor]:
        raise _fail("file ends inside the header (truncated?)", p)
    compressed = bool(format_byte & 0x80)
    point_format = format_byte & 0x3F
    if point_format not in POINT_RECORD_SIZES:
        raise _fail(f"point format {point_format} is not a LAS point format (0-10)", p)
    if minor < MIN_MINOR_VERSION[point_format]:
        raise _fail(f"point format {point_format} needs LAS 1.{MIN_MINOR_VERSION[point_format]} or later, "
                    f"the header says 1.{minor}", p)
    if record_length < POINT_RECORD_SIZES[point_format]:
        raise _fail(f"point record length {record_length} is shorter than point format {point_format}'s "
                    f"{POINT_RECORD_SIZES[point_format]} bytes", p)
    scales = struct.unpack_from("<3d", head, 131)
    offsets = struct.unpack_from("<3d", head, 155)
    for axis, s, o in zip("xyz", scales, offsets, strict=True):
        if not (math.isfinite(s) and MIN_SCALE <= s <= MAX_SCALE):
            raise _fail(f"{axis} scale {s!r} is not a usable coordinate resolution "
                        f"(finite, {MIN_SCALE:g} .. {MAX_SCALE:g} m)", p)
        if not (math.isfinite(o) and abs(o) <= MAX_ABS_OFFSET):
            raise _fail(f"{axis} offset {o!r} is not finite or beyond {MAX_ABS_OFFSET:g} m", p)
    n_points = legacy_count
    evlr_start = n_evlrs = 0
    if minor >= 4:
        evlr_start, n_evlrs, count64 = struct.unpack_from("<QIQ", head, 235)
        if legacy_count and count64 != legacy_count:
            raise _fail(f"the header's two point counts differ ({legacy_count:,} and {count64:,})", p)
        n_points = count64
    if n_points == 0:
        raise _fail("the header says the file holds no points", p)
    if offset_to_points < header_size or offset_to_points > size:
        raise _fail(f"offset to the point data ({offset_to_points:,}) lies outside the file "
                    f"(header {header_size} bytes, file {size:,} bytes)", p)

    laszip = None
    position = header_size
    for k in range(n_vlrs):
        vlr = _read_at(f, position, VLR_HEADER_SIZE, offset_to_points, f"VLR {k + 1} of {n_vlrs}", p)
        user_id = vlr[2:18].split(b"\0", 1)[0].decode("ascii", errors="replace")
        record_id, length = struct.unpack_from("<HH", vlr, 18)
        body = position + VLR_HEADER_SIZE
        if body + length > offset_to_points:
            raise _fail(f"VLR {k + 1} of {n_vlrs} runs past the start of the point data", p)
        if user_id == LASZIP_USER_ID and record_id == LASZIP_RECORD_ID:
            laszip = _read_at(f, body, length, size, "LASzip VLR", p)
        position = body + length

    end_of_points = size
    if n_evlrs:
        if evlr_start < offset_to_points or evlr_start + n_evlrs * EVLR_HEADER_SIZE > size:
            raise _fail(f"{n_evlrs:,} extended VLRs from byte {evlr_start:,} do not fit the file ({size:,} bytes)", p)
        position = evlr_start
        for k in range(n_evlrs):
            evlr = _read_at(f, position, EVLR_HEADER_SIZE, size, f"extended VLR {k + 1} of {n_evlrs}", p)
            (length,) = struct.unpack_from("<Q", evlr, 20)
            position += EVLR_HEADER_SIZE + length
            if position > size:
                raise _fail(f"extended VLR {k + 1} of {n_evlrs} runs past the end of the file", p)
        end_of_points = evlr_start

    facts = LasFileFacts((major, minor), point_format, record_length, n_points, compressed, offset_to_points)
    if not compressed:
        available = (end_of_points - offset_to_points) // record_length
        if n_points > available:
            raise _fail(f"the header says {n_points:,} points, the file holds {available:,} (truncated?)", p)
        waveform = struct.unpack_from("<Q", head, 227)[0] if minor == 3 else 0
        if n_points < available and not waveform and not n_evlrs:
            raise _fail(f"the header says {n_points:,} points, but the point data holds {available:,}", p)
        return facts
    return _check_laz(f, size, p, facts, laszip, end_of_points)


def _check_laz(f, size: int, p: Path, facts: LasFileFacts, laszip: bytes | None,  # type: ignore[no-untyped-def]
               end_of_points: int) -> LasFileFacts:
    if laszip is None or len(laszip) < 34:
        raise _fail("compressed point format without a (complete) LASzip VLR", p)
    (chunk_size,) = struct.unpack_from("<I", laszip, 12)
    (n_items,) = struct.unpack_from("<H", laszip, 32)
    if len(laszip) < 34 + 6 * n_items:
        raise _fail(f"the LASzip VLR lists {n_items} items but holds {(len(laszip) - 34) // 6}", p)
    item_bytes = sum(struct.unpack_from("<H", laszip, 34 + 6 * k + 2)[0] for k in range(n_items))
    if item_bytes != facts.record_length:
        raise _fail(f"the LASzip items make {item_bytes}-byte points, the header says {facts.record_length}", p)
    start = facts.offset_to_points
    (table_offset,) = struct.unpack("<q", _read_at(f, start, 8, size, "chunk table offset", p))
    if table_offset == -1:  # written at the end, when the writer could not seek back
        (table_offset,) = struct.unpack("<q", _read_at(f, size - 8, 8, size, "chunk table offset", p))
    if not start + 8 <= table_offset <= size - 8:
        raise _fail(f"the chunk table offset {table_offset:,} lies outside the point data "
                    f"({start + 8:,} .. {size - 8:,}; truncated or damaged?)", p)
    version, n_chunks = struct.unpack("<II", _read_at(f, table_offset, 8, size, "chunk table", p))
    compressed_bytes = table_offset - start - 8
    if version != 0 or n_chunks == 0 or n_chunks > compressed_bytes:
        raise _fail(f"the chunk table (version {version}, {n_chunks:,} chunks) does not fit the "
                    f"{compressed_bytes:,} bytes of compressed points (truncated or damaged?)", p)
    n = facts.n_points
    if chunk_size != VARIABLE_CHUNK_SIZE:
        if chunk_size == 0:
            raise _fail("the LASzip VLR gives a chunk size of 0 points", p)
        if not (n_chunks - 1) * chunk_size < n <= n_chunks * chunk_size:
            raise _fail(f"the header's point count {n:,} does not fit the chunk table ({n_chunks:,} chunks of "
                        f"{chunk_size:,} points)", p)
    elif n_chunks > n:
        raise _fail(f"the chunk table lists {n_chunks:,} chunks for {n:,} points", p)
    # The entries are arithmetic-coded: lazrs decodes them (safe now that their number is bounded).
    f.seek(start)
    try:
        table = lazrs.read_chunk_table(f, lazrs.LazVlr(laszip))
    except (lazrs.LazrsError, OSError, ValueError, MemoryError, OverflowError) as e:
        raise _fail(f"cannot read the chunk table (truncated or damaged?): {_first_line(e)}", p) from None
    if sum(int(b) for _, b in table) != compressed_bytes:
        raise _fail(f"the chunk table's {n_chunks:,} chunks make {sum(int(b) for _, b in table):,} bytes, the "
                    f"compressed points {compressed_bytes:,} (damaged?)", p)
    if chunk_size == VARIABLE_CHUNK_SIZE:
        stored = sum(int(c) for c, _ in table)
    elif facts.point_format >= 6:
        # Layered chunks (point formats 6-10) start with the first point raw, then its point count.
        last = start + 8 + sum(int(b) for _, b in table[:-1]) + facts.record_length
        (last_count,) = struct.unpack("<I", _read_at(f, last, 4, size, "last chunk", p))
        stored = (n_chunks - 1) * chunk_size + last_count
    else:
        stored = n  # formats 0-5 store no count in the chunks: the check above is all there is
    if stored != n:
        raise _fail(f"the header says {n:,} points, the compressed chunks hold {stored:,}", p)
    return LasFileFacts(facts.version, facts.point_format, facts.record_length, facts.n_points, True,
                        facts.offset_to_points, n_chunks, chunk_size)
