"""Seeded mutants of every input kinreg reads, and a runner that feeds them to the ``kinreg``
command in a subprocess (so that a signal, a Rust abort or a hang is seen as what it is).

A :class:`Mutant` knows whether it is *known to be wrong* (a truncated file, a header field that
contradicts the file, a NaN where a number must be): such a mutant must never end with exit 0.
Random bit flips inside point records or free text may leave a valid file, so they are not
marked wrong; they must still end cleanly (exit 0 or 1, no traceback, no internal error).

Outcome classes (:func:`classify`): ``accepted`` (exit 0), ``refused`` (exit 1), ``internal``
(exit 2), ``traceback`` (a Python traceback on stderr), ``signal`` (killed by a signal, e.g.
SIGABRT), ``hang`` (timeout), ``other`` (any other exit code).
"""

from __future__ import annotations

import os
import struct
import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np
from pye57 import libe57

ROOT = Path(__file__).resolve().parents[1]
REALDATA = ROOT.parent / "shared" / "realdata"


@dataclass(frozen=True)
class Mutant:
    name: str
    data: bytes
    suffix: str
    wrong: bool  # known to be wrong: must not be accepted


@dataclass(frozen=True)
class Outcome:
    mutant: str
    kind: str  # accepted, refused, internal, traceback, signal, hang, other
    returncode: int | None
    lines: tuple[str, ...]  # stderr lines without progress bars
    names_file: bool

    def __str__(self) -> str:
        return f"{self.mutant}: {self.kind} (exit {self.returncode}): " + " | ".join(self.lines[:4])


# --------------------------------------------------------------------------- running


def run_kinreg(args: list[object], timeout_s: float = 120.0) -> tuple[int | None, str, str]:
    """``python -m kinreg_cli ARGS`` with this checkout's code; (exit code or None on timeout,
    stdout, stderr). A negative code is the signal that ended the process."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "cli")])
    env.pop("KINREG_DEBUG", None)
    env["COLUMNS"] = "200"
    try:
        done = subprocess.run([sys.executable, "-m", "kinreg_cli", *map(str, args)], capture_output=True,
                              text=True, errors="replace", env=env, timeout=timeout_s, check=False)
    except subprocess.TimeoutExpired as e:
        return None, str(e.stdout or ""), str(e.stderr or "")
    return done.returncode, done.stdout, done.stderr


def message_lines(stderr: str) -> tuple[str, ...]:
    """stderr without rich's progress bars (drawn with '━')."""
    return tuple(line for line in stderr.splitlines() if line.strip() and "━" not in line)


def classify(name: str, code: int | None, stderr: str, path: Path) -> Outcome:
    lines = message_lines(stderr)
    names_file = any(str(path) in line for line in lines)
    if code is None:
        kind = "hang"
    elif code < 0:
        kind = "signal"
    elif "Traceback (most recent call last)" in stderr:
        kind = "traceback"
    elif code == 0:
        kind = "accepted"
    elif code == 1:
        kind = "refused"
    elif code == 2:
        kind = "internal"
    else:
        kind = "other"
    return Outcome(name, kind, code, lines, names_file)


def run_mutant(mutant: Mutant, folder: Path, args: Callable[[Path], list[object]], timeout_s: float = 120.0
               ) -> Outcome:
    """Write ``mutant`` into ``folder`` and run ``kinreg`` with ``args(path)``."""
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in mutant.name)
    path = folder / f"{safe}{mutant.suffix}"
    path.write_bytes(mutant.data)
    code, _, err = run_kinreg(args(path), timeout_s)
    return classify(mutant.name, code, err, path)


def problems(outcomes: list[Outcome], mutants: dict[str, Mutant]) -> list[str]:
    """Every outcome that breaks the contract, as one line each (empty: all good)."""
    bad = []
    for o in outcomes:
        m = mutants[o.mutant]
        if o.kind in ("signal", "traceback", "internal", "hang", "other"):
            bad.append(f"{o}")
        elif o.kind == "accepted" and m.wrong:
            bad.append(f"{o} -- a wrong input was accepted")
        elif o.kind == "refused" and (len(o.lines) > 2 or not o.names_file):
            bad.append(f"{o} -- a refusal must be at most 2 lines naming the file")
    return bad


def tally(outcomes: list[Outcome]) -> dict[str, int]:
    counts: dict[str, int] = {}
    for o in outcomes:
        counts[o.kind] = counts.get(o.kind, 0) + 1
    return counts


# --------------------------------------------------------------------------- base files


def small_las(path: Path, n_points: int = 120_000, point_format: int = 6, seed: int = 1,
              t0_s: float = 1623220971.0, duration_s: float = 12.0) -> Path:
    """A LAS/LAZ (by suffix) with time-sorted gps_time; 120,000 points make 3 LAZ chunks."""
    rng = np.random.default_rng(seed)
    header = laspy.LasHeader(point_format=point_format, version="1.4" if point_format >= 6 else "1.2")
    header.scales = np.array([1e-4, 1e-4, 1e-4])
    header.offsets = np.array([0.0, 0.0, 0.0])
    las = laspy.LasData(header)
    xyz = rng.uniform(-20.0, 20.0, (n_points, 3))
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.gps_time = np.sort(rng.uniform(t0_s, t0_s + duration_s, n_points))
    las.intensity = rng.integers(0, 65535, n_points, dtype=np.uint16)
    las.write(path)
    return path


def crc32c(data: bytes) -> int:
    """CRC-32C (Castagnoli), the checksum of every E57 page."""
    crc = 0xFFFFFFFF
    table = _crc_table()
    for byte in data:
        crc = table[(crc ^ byte) & 0xFF] ^ (crc >> 8)
    return crc ^ 0xFFFFFFFF


_TABLE: list[int] = []


def _crc_table() -> list[int]:
    if not _TABLE:
        for i in range(256):
            c = i
            for _ in range(8):
                c = (c >> 1) ^ 0x82F63B78 if c & 1 else c >> 1
            _TABLE.append(c)
    return _TABLE


E57_PAGE = 1024
E57_PAYLOAD = 1020


def e57_fix_checksums(data: bytearray, offsets: list[int] | None = None) -> bytearray:
    """Recompute the CRC (big endian, last 4 bytes of each 1024-byte page) of every page, or of
    the pages holding ``offsets``."""
    pages = range(0, len(data) - E57_PAGE + 1, E57_PAGE) if offsets is None else sorted(
        {o // E57_PAGE * E57_PAGE for o in offsets if o // E57_PAGE * E57_PAGE + E57_PAGE <= len(data)})
    for start in pages:
        data[start + E57_PAYLOAD:start + E57_PAGE] = struct.pack(">I", crc32c(bytes(data[start:start + E57_PAYLOAD])))
    return data


def e57_payload_offsets(size: int) -> np.ndarray:
    """Physical offsets of all payload (non-checksum) bytes."""
    offsets = np.arange(size)
    return offsets[offsets % E57_PAGE < E57_PAYLOAD]


def write_e57(path: Path, n_scans: int = 1, n_points: int = 200, bounds_as_string: bool = False,
              pose: bool = True, xyz: np.ndarray | None = None, seed: int = 2) -> Path:
    """A small E57 with ``n_scans`` scans of ``n_points`` cartesian points, a pose each, and
    cartesianBounds (as Float nodes, or as String nodes with ``bounds_as_string``)."""
    rng = np.random.default_rng(seed)
    imf = libe57.ImageFile(str(path), "w")
    try:
        root = imf.root()
        root.set("formatName", libe57.StringNode(imf, "ASTM E57 3D Imaging Data File"))
        root.set("guid", libe57.StringNode(imf, "{fuzz-base}"))
        root.set("versionMajor", libe57.IntegerNode(imf, 1))
        root.set("versionMinor", libe57.IntegerNode(imf, 0))
        data3d = libe57.VectorNode(imf, True)
        root.set("data3D", data3d)
        for k in range(n_scans):
            points_xyz = rng.uniform(-5.0, 5.0, (n_points, 3)) if xyz is None else xyz
            entry = libe57.StructureNode(imf)
            entry.set("guid", libe57.StringNode(imf, f"{{scan-{k}}}"))
            entry.set("name", libe57.StringNode(imf, f"scan {k}"))
            if pose:
                p = libe57.StructureNode(imf)
                rotation = libe57.StructureNode(imf)
                for axis, value in zip("wxyz", (1.0, 0.0, 0.0, 0.0), strict=True):
                    rotation.set(axis, libe57.FloatNode(imf, value))
                translation = libe57.StructureNode(imf)
                for axis in "xyz":
                    translation.set(axis, libe57.FloatNode(imf, float(k)))
                p.set("rotation", rotation)
                p.set("translation", translation)
                entry.set("pose", p)
            bounds = libe57.StructureNode(imf)
            for a, column in zip("xyz", points_xyz.T, strict=True):
                for m, value in (("Minimum", float(np.nanmin(column))), ("Maximum", float(np.nanmax(column)))):
                    node = libe57.StringNode(imf, f"{value}") if bounds_as_string else libe57.FloatNode(imf, value)
                    bounds.set(f"{a}{m}", node)
            entry.set("cartesianBounds", bounds)
            prototype = libe57.StructureNode(imf)
            for name in ("cartesianX", "cartesianY", "cartesianZ", "timeStamp"):
                prototype.set(name, libe57.FloatNode(imf, 0.0, libe57.E57_DOUBLE))
            points = libe57.CompressedVectorNode(imf, prototype, libe57.VectorNode(imf, True))
            entry.set("points", points)
            data3d.append(entry)
            buffers = libe57.VectorSourceDestBuffer()
            columns = [np.ascontiguousarray(points_xyz[:, i], dtype=np.float64) for i in range(3)]
            columns.append(np.linspace(0.0, 1.0, len(points_xyz)) + k)
            for name, array in zip(("cartesianX", "cartesianY", "cartesianZ", "timeStamp"), columns, strict=True):
                buffers.append(libe57.SourceDestBuffer(imf, name, array, len(array), True, True))
            writer = points.writer(buffers)
            writer.write(len(points_xyz))
            writer.close()
    finally:
        imf.close()
    return path


def e57_first_data_packet(data: bytes) -> int:
    """Physical offset of the first data packet of the first compressed vector (its type byte)."""
    xml_offset, xml_length = struct.unpack_from("<QQ", data, 24)
    xml = _e57_logical(data, xml_offset, xml_length).decode("utf-8")
    start = xml.index('fileOffset="') + len('fileOffset="')
    section = int(xml[start:xml.index('"', start)])
    header = _e57_logical(data, section, 32)
    (data_offset,) = struct.unpack_from("<Q", header, 16)
    return int(data_offset)


def _e57_logical(data: bytes, physical: int, n: int) -> bytes:
    out = bytearray()
    p = physical
    while len(out) < n:
        in_page = p % E57_PAGE
        take = min(E57_PAYLOAD - in_page, n - len(out))
        out += data[p:p + take]
        p += take + (E57_PAGE - E57_PAYLOAD if in_page + take == E57_PAYLOAD else 0)
    return bytes(out)


# --------------------------------------------------------------------------- LAS/LAZ mutants

# Fixed header fields (LAS 1.4 R15): name -> (offset, struct format)
LAS_FIELDS = {
    "version_minor": (25, "<B"),
    "header_size": (94, "<H"),
    "offset_to_points": (96, "<I"),
    "n_vlrs": (100, "<I"),
    "point_format": (104, "<B"),
    "record_length": (105, "<H"),
    "legacy_count": (107, "<I"),
    "scale_x": (131, "<d"), "scale_y": (139, "<d"), "scale_z": (147, "<d"),
    "offset_x": (155, "<d"), "offset_y": (163, "<d"), "offset_z": (171, "<d"),
    "evlr_start": (235, "<Q"),
    "n_evlrs": (243, "<I"),
    "count64": (247, "<Q"),
}  # fmt: skip


def _set(data: bytes, field: str, value: float | int) -> bytes:
    offset, fmt = LAS_FIELDS[field]
    out = bytearray(data)
    struct.pack_into(fmt, out, offset, value)
    return bytes(out)


def _get(data: bytes, field: str) -> float | int:
    offset, fmt = LAS_FIELDS[field]
    return struct.unpack_from(fmt, data, offset)[0]  # type: ignore[no-any-return]


def las_header_mutants(base: bytes, tag: str, suffix: str) -> Iterator[Mutant]:
    """Deterministic header edits, every one of them wrong."""
    minor = int(_get(base, "version_minor"))
    compressed = suffix == ".laz"
    count_field = "count64" if minor >= 4 else "legacy_count"
    n = int(_get(base, count_field))
    for axis in "xyz":
        for value in (0.0, -0.001, float("nan"), float("inf"), 1e300):
            yield Mutant(f"{tag}/scale_{axis}={value}", _set(base, f"scale_{axis}", value), suffix, True)
        for value in (float("nan"), float("inf"), -float("inf"), 1e300):
            yield Mutant(f"{tag}/offset_{axis}={value}", _set(base, f"offset_{axis}", value), suffix, True)
    point_format = int(_get(base, "point_format")) & 0x3F
    for value in (0, 1, n - 1, n + 1, 2**32 - 1):
        data = _set(base, count_field, value)
        if minor >= 4 and _get(base, "legacy_count"):
            data = _set(data, "legacy_count", min(value, 2**32 - 1))
        # LAZ point formats 0-5 store no point count in their chunks: a count lowered by less than
        # the last chunk's points cannot be told from the file (kinreg reads that many points).
        undetectable = compressed and point_format < 6 and n - 50_000 < value < n and n > 50_000
        yield Mutant(f"{tag}/point_count={value}", data, suffix, not undetectable)
    if minor >= 4:
        yield Mutant(f"{tag}/count64=2**63", _set(base, "count64", 2**63), suffix, True)
    for value in range(10):
        if value == minor:
            continue
        needs = {0: 0, 1: 0, 2: 2, 3: 2, 4: 3, 5: 3}.get(int(_get(base, "point_format")) & 0x3F, 4)
        sizes = {0: 227, 1: 227, 2: 227, 3: 235, 4: 375}
        wrong = value > 4 or value < needs or int(_get(base, "header_size")) < sizes[value] or (
            minor >= 4 and value < 4)  # the 1.4 point count would be lost
        yield Mutant(f"{tag}/version_minor={value}", _set(base, "version_minor", value), suffix, wrong)
    if minor >= 4:
        for value in (1, 1000, 2**32 - 1):
            yield Mutant(f"{tag}/n_evlrs={value}", _set(base, "n_evlrs", value), suffix, True)
        yield Mutant(f"{tag}/evlr_start=huge", _set(_set(base, "n_evlrs", 1), "evlr_start", 2**62), suffix, True)
    for value in (0, 10, int(_get(base, "offset_to_points")) + 1, 2**32 - 1):
        yield Mutant(f"{tag}/offset_to_points={value}", _set(base, "offset_to_points", value), suffix, True)
    for value in (int(_get(base, "n_vlrs")) + 1, 2**32 - 1):
        yield Mutant(f"{tag}/n_vlrs={value}", _set(base, "n_vlrs", value), suffix, True)
    for value in (0, 1, int(_get(base, "record_length")) + 1, 65535):
        yield Mutant(f"{tag}/record_length={value}", _set(base, "record_length", value), suffix, True)
    for value in (11, 63):
        flag = int(_get(base, "point_format")) & 0xC0
        yield Mutant(f"{tag}/point_format={value}", _set(base, "point_format", flag | value), suffix, True)
    yield Mutant(f"{tag}/header_size=100", _set(base, "header_size", 100), suffix, True)
    if compressed:
        yield from _chunk_table_mutants(base, tag, suffix)


def _chunk_table_mutants(base: bytes, tag: str, suffix: str) -> Iterator[Mutant]:
    start = int(_get(base, "offset_to_points"))
    (table,) = struct.unpack_from("<q", base, start)
    for value in (0, -1, start, table + 1, table - 1, len(base), 2**62):
        out = bytearray(base)
        struct.pack_into("<q", out, start, value)
        yield Mutant(f"{tag}/chunk_table_offset={value}", bytes(out), suffix, True)
    for value in (0, 2**31, 2**32 - 1, 1_000_000):
        out = bytearray(base)
        struct.pack_into("<I", out, table + 4, value)
        yield Mutant(f"{tag}/n_chunks={value}", bytes(out), suffix, True)
    for k in range(0, 16):
        # one byte deleted inside the chunk table (the file is then one byte short)
        cut = table + k
        if cut < len(base):
            yield Mutant(f"{tag}/chunk_table_delete_byte_{k}", base[:cut] + base[cut + 1:], suffix, True)
    yield Mutant(f"{tag}/chunk_table_cut", base[:table + 4], suffix, True)


def bit_flip_mutants(base: bytes, tag: str, suffix: str, rng: np.random.Generator, n: int,
                     region: tuple[int, int] | None = None) -> Iterator[Mutant]:
    """``n`` mutants with 1-8 random bits flipped (in ``region`` if given); not known wrong."""
    lo, hi = region or (0, len(base))
    for k in range(n):
        out = bytearray(base)
        for _ in range(int(rng.integers(1, 9))):
            i = int(rng.integers(lo, min(hi, len(base))))
            out[i] ^= 1 << int(rng.integers(0, 8))
        yield Mutant(f"{tag}/bitflip_{k}", bytes(out), suffix, False)


def truncation_mutants(base: bytes, tag: str, suffix: str, rng: np.random.Generator, n: int) -> Iterator[Mutant]:
    """``n`` truncations at random lengths (always wrong: the file ends early)."""
    for k in range(n):
        cut = int(rng.integers(0, len(base) - 1))
        yield Mutant(f"{tag}/truncate_{k}_at_{cut}", base[:cut], suffix, True)


def las_time_mutants(path: Path, tag: str, rng: np.random.Generator, share: float) -> Mutant:
    """The file rewritten with ``share`` of its points' gps_time set to NaN or inf."""
    las = laspy.read(path)
    t = np.array(las.gps_time)
    idx = rng.choice(len(t), max(1, int(share * len(t))), replace=False)
    t[idx] = rng.choice([np.nan, np.inf, -np.inf], len(idx))
    las.gps_time = t
    out = path.parent / f"_time_{share}{path.suffix}"
    las.write(out)
    return Mutant(f"{tag}/nonfinite_time_share={share}", out.read_bytes(), path.suffix, share > 0.05)


# --------------------------------------------------------------------------- E57 mutants


def e57_mutants(base: bytes, tag: str, rng: np.random.Generator, n_flips: int, n_fixed: int, n_cut: int,
                points_read: bool = True) -> Iterator[Mutant]:
    """Bit flips without checksum repair, bit flips with the checksums recomputed (neither known
    wrong: a flip may hit a page no reader verifies, or a value), truncations, header field edits,
    data packet types that do not exist (wrong where the command reads the points: ``points_read``)."""
    yield from bit_flip_mutants(base, f"{tag}/raw", ".e57", rng, n_flips, (48, len(base)))
    payload = e57_payload_offsets(len(base))
    payload = payload[payload >= 48]
    for k in range(n_fixed):
        out = bytearray(base)
        flipped = []
        for _ in range(int(rng.integers(1, 4))):
            i = int(rng.choice(payload))
            out[i] ^= 1 << int(rng.integers(0, 8))
            flipped.append(i)
        yield Mutant(f"{tag}/crcfixed_bitflip_{k}", bytes(e57_fix_checksums(out, flipped)), ".e57", False)
    yield from truncation_mutants(base, tag, ".e57", rng, n_cut)
    for field, offset, fmt, values in (("physical_length", 16, "<Q", (0, len(base) + 1024, 2**63)),
                                       ("xml_offset", 24, "<Q", (0, len(base), 2**62)),
                                       ("xml_length", 32, "<Q", (0, 2**40)),
                                       ("page_size", 40, "<Q", (0, 1, 4096))):
        for value in values:
            out = bytearray(base)
            struct.pack_into(fmt, out, offset, value)
            yield Mutant(f"{tag}/{field}={value}", bytes(e57_fix_checksums(out, [offset])), ".e57", True)
    packet = e57_first_data_packet(base)
    for value in (3, 255):
        out = bytearray(base)
        out[packet] = value
        yield Mutant(f"{tag}/data_packet_type={value}", bytes(e57_fix_checksums(out, [packet])), ".e57",
                     points_read)


# --------------------------------------------------------------------------- text mutants


def trajectory_mutants(text: str, tag: str, rng: np.random.Generator, n_random: int) -> Iterator[Mutant]:
    """Edits of a GeoSLAM text trajectory: known-wrong values and random byte damage."""
    lines = text.splitlines()
    header, rows = lines[0], lines[1:]

    def with_rows(new_rows: list[str], head: str = header) -> bytes:
        return ("\n".join([head, *new_rows]) + "\n").encode()

    def field(row: str, i: int, value: str) -> str:
        parts = row.split()
        parts[i] = value
        return " ".join(parts)

    k = len(rows) // 2
    for value in ("nan", "inf", "-inf", "1e400"):
        for i in (0, 1, 4):
            edited = list(rows)
            edited[k] = field(rows[k], i, value)
            yield Mutant(f"{tag}/row_{k}_col_{i}={value}", with_rows(edited), ".txt", True)
    yield Mutant(f"{tag}/all_times_equal", with_rows([field(r, 0, rows[0].split()[0]) for r in rows]), ".txt", True)
    yield Mutant(f"{tag}/time_repeats", with_rows(rows[:k] + [rows[k - 1]] + rows[k:]), ".txt", True)
    yield Mutant(f"{tag}/time_goes_back", with_rows(rows[:k] + [rows[k + 1], rows[k]] + rows[k + 2:]), ".txt", True)
    yield Mutant(f"{tag}/quaternion_x2", with_rows(
        rows[:k] + [field(field(field(field(rows[k], 4, "2"), 5, "0"), 6, "0"), 7, "0")] + rows[k + 1:]), ".txt", True)
    yield Mutant(f"{tag}/quaternion_zero", with_rows(
        rows[:k] + [field(field(field(field(rows[k], 4, "0"), 5, "0"), 6, "0"), 7, "0")] + rows[k + 1:]), ".txt", True)
    yield Mutant(f"{tag}/short_row", with_rows(rows[:k] + [" ".join(rows[k].split()[:5])] + rows[k + 1:]), ".txt",
                 True)
    yield Mutant(f"{tag}/one_row", with_rows(rows[:1]), ".txt", True)
    yield Mutant(f"{tag}/header_only", with_rows([]), ".txt", True)
    yield Mutant(f"{tag}/partial_header", with_rows(rows, "%time x y z"), ".txt", True)
    yield Mutant(f"{tag}/binary", bytes(rng.integers(0, 256, 4000, dtype=np.uint8)), ".txt", True)
    data = text.encode()
    yield from bit_flip_mutants(data, tag, ".txt", rng, n_random)
    for j in range(max(1, n_random // 4)):
        cut = int(rng.integers(len(header) + 1, len(data) - 1))
        # cut inside a row (not after a newline, which leaves a valid shorter file)
        while data[cut - 1:cut] == b"\n":
            cut -= 1
        yield Mutant(f"{tag}/truncate_{j}_at_{cut}", data[:cut], ".txt", data[cut:cut + 1] != b"\n" and
                     len(data[:cut].split(b"\n")[-1].split()) < 8)


def toml_mutants(text: str, tag: str, rng: np.random.Generator, n_random: int, key: str, deep: int = 100_000
                 ) -> Iterator[Mutant]:
    """TOML damage: deep nesting, non-finite numbers and wrong types for the number ``key``,
    random byte damage."""
    yield Mutant(f"{tag}/nested_array_{deep}", (text + f"\nx = {'[' * deep}{']' * deep}\n").encode(), ".toml", True)
    yield Mutant(f"{tag}/nested_table_{deep // 100}",
                 (text + "\ny = " + "{a = " * (deep // 100) + "1" + "}" * (deep // 100) + "\n").encode(), ".toml", True)
    for value in ("nan", "inf", "-inf", "+nan", '"0.05"', "1e400"):
        edited = _replace_number(text, key, value)
        assert edited != text, key
        yield Mutant(f"{tag}/{key}={value}", edited.encode(), ".toml", True)
    yield Mutant(f"{tag}/binary", bytes(rng.integers(0, 256, 2000, dtype=np.uint8)), ".toml", True)
    yield from bit_flip_mutants(text.encode(), tag, ".toml", rng, n_random)


def _replace_number(text: str, key: str, value: str) -> str:
    import re

    return re.sub(rf"(?m)^({key}\s*=\s*)-?[0-9][0-9.eE+-]*", lambda m: m.group(1) + value, text, count=1)
