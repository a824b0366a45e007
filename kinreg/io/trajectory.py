"""Trajectory readers and writers: GeoSLAM text, TUM, PLY (ASCII and binary), CSV with a mapping.

Every reader returns a validated :class:`~kinreg.types.Trajectory`:

- times strictly increasing (the first offending row is named by its line in the file),
- all values finite,
- quaternions of unit norm: renormalised where ``|1 - |q|| <= 1e-3``, rejected beyond,
- quaternion signs made continuous (q and -q are the same rotation; a flip would break
  interpolation).

Row numbers in messages are 1-based line numbers of the file (header lines count).
"""

from __future__ import annotations

import csv
import enum
import io
import logging
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from kinreg.errors import TrajectoryError
from kinreg.geometry import FloatArray, Pose, make_quat_continuous
from kinreg.types import Trajectory

log = logging.getLogger(__name__)

QUAT_NORM_TOLERANCE = 1e-3

# kinreg's column names, in the order the arrays are built from.
COLUMNS = ("time", "x", "y", "z", "qw", "qx", "qy", "qz")


class TrajectoryFormat(enum.Enum):
    GEOSLAM = "geoslam"
    TUM = "tum"
    PLY = "ply"
    CSV = "csv"


def read_trajectory(
    path: str | Path,
    fmt: TrajectoryFormat | str | None = None,
    columns: Mapping[str, str | int] | None = None,
) -> Trajectory:
    """Read and validate a trajectory file.

    ``fmt`` is guessed when ``None``: ``.ply`` is PLY, ``.csv`` is CSV, ``.tum`` or a ``#``
    header ending in ``qw`` is TUM, anything else GeoSLAM text. ``columns`` maps kinreg's names
    (``time x y z qw qx qy qz``) to CSV header names or 0-based column indices (CSV only; without
    it common header names are recognised).

    Raises :class:`TrajectoryError` naming the file and, where it applies, the row.
    """
    p = Path(path)
    if not p.exists():
        raise TrajectoryError("file not found", p)
    if p.is_dir():
        raise TrajectoryError("is a folder, not a trajectory file", p)
    kind = _guess_format(p) if fmt is None else TrajectoryFormat(fmt)
    try:
        if kind is TrajectoryFormat.PLY:
            table, lines = _read_ply(p)
        elif kind is TrajectoryFormat.CSV:
            table, lines = _read_csv(p, columns)
        else:
            table, lines = _read_text(p, kind)
    except UnicodeDecodeError:
        raise TrajectoryError("not a text file (cannot decode as UTF-8)", p) from None
    except OSError as e:
        raise TrajectoryError(f"cannot read: {e.strerror or e}", p) from None
    return _validated(table, lines, p)


def _guess_format(p: Path) -> TrajectoryFormat:
    suffix = p.suffix.lower()
    if suffix == ".ply":
        return TrajectoryFormat.PLY
    if suffix == ".csv":
        return TrajectoryFormat.CSV
    if suffix == ".tum":
        return TrajectoryFormat.TUM
    with open(p, encoding="utf-8", errors="replace") as f:
        for line in f:
            s = line.strip()
            if not s:
                continue
            if s.startswith("#") and s.lower().split()[-1:] == ["qw"]:
                return TrajectoryFormat.TUM
            break
    return TrajectoryFormat.GEOSLAM


def _parse_rows(
    rows: Sequence[tuple[int, list[str]]], n_cols: int, p: Path
) -> tuple[FloatArray, np.ndarray]:
    """Convert the first ``n_cols`` fields of each (line number, fields) row to float64."""
    table = np.empty((len(rows), n_cols))
    lines = np.empty(len(rows), dtype=np.int64)
    for k, (line_no, fields) in enumerate(rows):
        if len(fields) < n_cols:
            raise TrajectoryError(f"row {line_no}: {len(fields)} values, expected at least {n_cols}", p)
        try:
            table[k] = [float(v) for v in fields[:n_cols]]
        except ValueError:
            bad = next(v for v in fields[:n_cols] if not _is_float(v))
            raise TrajectoryError(f"row {line_no}: '{bad}' is not a number", p) from None
        lines[k] = line_no
    return table, lines


def _is_float(v: str) -> bool:
    try:
        float(v)
    except ValueError:
        return False
    return True


def _read_text(p: Path, kind: TrajectoryFormat) -> tuple[FloatArray, np.ndarray]:
    """GeoSLAM (t x y z q0 q1 q2 q3 ...) or TUM (t x y z qx qy qz qw) whitespace text.

    A header line (``%`` or ``#``) that names the columns decides their order, whatever the
    format: ``%time x y z qx qy qz qw`` is read as scalar-last. Without one, the format's order.
    """
    rows: list[tuple[int, list[str]]] = []
    order: list[int] | None = None
    with open(p, encoding="utf-8") as f:
        for line_no, line in enumerate(f, start=1):
            s = line.strip()
            if not s:
                continue
            if s[0] in "%#":
                if not rows:  # a header names the columns of the rows after it
                    order = _header_order(s, line_no, p) or order
                continue
            rows.append((line_no, s.replace(",", " ").split()))
    if order is not None:
        width = max(order) + 1
        table, lines = _parse_rows([(n, f[:width]) for n, f in rows], width, p)
        return table[:, order], lines
    table, lines = _parse_rows(rows, 8, p)
    if kind is TrajectoryFormat.TUM:
        table = table[:, [0, 1, 2, 3, 7, 4, 5, 6]]
    return table, lines


def _header_order(line: str, line_no: int, p: Path) -> list[int] | None:
    """The file columns of ``time x y z qw qx qy qz`` named by a ``%``/``#`` header line, or
    ``None`` for a comment (fewer than four of kinreg's columns named). A header that names
    some columns but not all is an error: guessing the rest could turn every orientation."""
    names = [n.lower().lstrip("%#") for n in line.lstrip("%#").replace(",", " ").split()]
    found: dict[str, int] = {}
    for key in COLUMNS:
        hits = [names.index(a) for a in _HEADER_ALIASES[key] if a in names]
        if hits:
            found[key] = min(hits)
    if len(found) < 4:
        return None
    missing = [key for key in COLUMNS if key not in found]
    if missing:
        raise TrajectoryError(f"header line {line_no} names no column for {', '.join(missing)} "
                              f"(has: {' '.join(names)})", p)
    if len(set(found.values())) < len(COLUMNS):
        raise TrajectoryError(f"header line {line_no} names one column twice ({' '.join(names)})", p)
    return [found[key] for key in COLUMNS]


_CSV_ALIASES: dict[str, tuple[str, ...]] = {
    "time": ("time", "t", "timestamp", "gps_time", "gpstime", "stamp", "%time", "#time"),
    "x": ("x", "tx", "pos_x", "easting", "e"),
    "y": ("y", "ty", "pos_y", "northing", "n"),
    "z": ("z", "tz", "pos_z", "height", "h"),
    "qw": ("qw", "q0", "quat_w", "w"),
    "qx": ("qx", "q1", "quat_x"),
    "qy": ("qy", "q2", "quat_y"),
    "qz": ("qz", "q3", "quat_z"),
}


_HEADER_ALIASES: dict[str, tuple[str, ...]] = {
    key: (*names, *(f"q_{n[1:]}" for n in names if n in ("qw", "qx", "qy", "qz")))
    for key, names in _CSV_ALIASES.items()
}


def _read_csv(p: Path, columns: Mapping[str, str | int] | None) -> tuple[FloatArray, np.ndarray]:
    text = p.read_text(encoding="utf-8")
    if not text.strip():
        raise TrajectoryError("file is empty", p)
    try:
        dialect = csv.Sniffer().sniff(text[:4096], delimiters=",;\t ")
        delimiter = dialect.delimiter
    except csv.Error:
        delimiter = ","
    reader = csv.reader(io.StringIO(text), delimiter=delimiter, skipinitialspace=True)
    try:
        all_rows = [(i, [c.strip() for c in r]) for i, r in enumerate(reader, start=1) if any(c.strip() for c in r)]
    except csv.Error as e:
        raise TrajectoryError(f"not a readable CSV file: {e}", p) from None
    if not all_rows:
        raise TrajectoryError("file has no values", p)
    header_line, header = all_rows[0]
    has_header = not all(_is_float(c) for c in header if c)
    data_rows = all_rows[1:] if has_header else all_rows
    names = [h.lower() for h in header] if has_header else []

    index: list[int] = []
    for key in COLUMNS:
        if columns is not None and key in columns:
            ref = columns[key]
            if isinstance(ref, int):
                index.append(ref)
                continue
            if ref.lower() not in names:
                raise TrajectoryError(f"column '{ref}' (for {key}) is not in the header line {header_line}", p)
            index.append(names.index(ref.lower()))
            continue
        if columns is not None and not has_header:
            raise TrajectoryError(f"the column mapping lacks '{key}' and the file has no header", p)
        found = [names.index(a) for a in _CSV_ALIASES[key] if a in names]
        if not found:
            if not has_header:
                index = list(range(8))  # no header: assume time x y z qw qx qy qz
                break
            raise TrajectoryError(
                f"no column for '{key}' in the header; give a column mapping (e.g. {key}=<name>)", p
            )
        index.append(found[0])
    picked = [(line_no, [fields[i] if i < len(fields) else "" for i in index]) for line_no, fields in data_rows]
    for line_no, fields in picked:
        if "" in fields:
            raise TrajectoryError(f"row {line_no}: missing value", p)
    return _parse_rows(picked, 8, p)


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip

_PLY_NAMES: dict[str, tuple[str, ...]] = {
    "time": ("time", "timestamp", "t", "gps_time", "gpstime", "stamp", "timestamp_s"),
    "x": ("x",), "y": ("y",), "z": ("z",),
    "qw": ("qw", "q0", "rot_w", "quat_w", "w"),
    "qx": ("qx", "q1", "rot_x", "quat_x"),
    "qy": ("qy", "q2", "rot_y", "quat_y"),
    "qz": ("qz", "q3", "rot_z", "quat_z"),
}  # fmt: skip


def _read_ply(p: Path) -> tuple[FloatArray, np.ndarray]:
    """PLY trajectory: a ``vertex`` element with time, x, y, z and quaternion properties."""
    with open(p, "rb") as f:
        if f.readline().strip() != b"ply":
            raise TrajectoryError("not a PLY file (no 'ply' magic line)", p)
        fmt = None
        elements: list[tuple[str, int, list[tuple[str, str]]]] = []
        n_header_lines = 1
        while True:
            raw = f.readline()
            if not raw:
                raise TrajectoryError("PLY header has no 'end_header'", p)
            n_header_lines += 1
            words = raw.decode("ascii", errors="replace").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "end_header":
                break
            if words[0] == "format" and len(words) >= 2:
                fmt = words[1]
            elif words[0] == "element":
                if len(words) != 3 or not words[2].isdigit():
                    raise TrajectoryError(f"PLY header line {n_header_lines}: expected 'element <name> <count>'", p)
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property" and elements:
                if len(words) >= 5 and words[1] == "list":
                    elements[-1][2].append((words[-1], "list"))
                elif len(words) == 3 and words[1] in _PLY_TYPES:
                    elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
                elif len(words) == 3 or (len(words) >= 2 and words[1] == "list"):
                    raise TrajectoryError(f"PLY property type '{words[1]}' is not supported", p)
                else:
                    raise TrajectoryError(
                        f"PLY header line {n_header_lines}: expected 'property <type> <name>'", p)
        if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
            raise TrajectoryError(f"PLY format '{fmt}' is not supported", p)
        if not elements or elements[0][0] != "vertex":
            raise TrajectoryError("the first PLY element must be 'vertex' (the poses)", p)
        _, n, props = elements[0]
        if any(t == "list" for _, t in props):
            raise TrajectoryError("list properties in the PLY vertex element are not supported", p)
        names = [name.lower() for name, _ in props]
        picks = []
        for key in COLUMNS:
            hit = [names.index(a) for a in _PLY_NAMES[key] if a in names]
            if not hit:
                raise TrajectoryError(f"PLY vertex element has no property for '{key}' (has: {', '.join(names)})", p)
            picks.append(hit[0])
        if fmt == "ascii":
            rows = []
            for k in range(n):
                line = f.readline()
                if not line:
                    raise TrajectoryError(f"PLY file ends after {k} of {n} vertices", p)
                fields = line.decode("ascii", errors="replace").split()
                rows.append((n_header_lines + k + 1, [fields[i] if i < len(fields) else "" for i in picks]))
            return _parse_rows(rows, 8, p)
        endian = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(f"p{i}", endian + t) for i, (_, t) in enumerate(props)])
        # Never ask for more than the file holds: a damaged count must not allocate terabytes.
        remaining = p.stat().st_size - f.tell()
        data = f.read(min(n * dtype.itemsize, max(remaining, 0)))
        if len(data) < n * dtype.itemsize:
            raise TrajectoryError(f"PLY file ends after {len(data) // dtype.itemsize} of {n} vertices", p)
        rec = np.frombuffer(data, dtype=dtype, count=n)
        table = np.column_stack([rec[f"p{i}"].astype(np.float64) for i in picks])
        # Binary rows have no line numbers; report vertex numbers (1-based) instead.
        return table, np.arange(1, n + 1)


def _validated(table: FloatArray, lines: np.ndarray, p: Path) -> Trajectory:
    if len(table) < 2:
        raise TrajectoryError(f"{len(table)} pose row(s); a trajectory needs at least two", p)
    bad = ~np.isfinite(table).all(axis=1)
    if bad.any():
        k = int(np.argmax(bad))
        raise TrajectoryError(f"row {lines[k]}: value is not finite (NaN or infinite)", p)
    stamps = table[:, 0]
    step = np.diff(stamps)
    if (step <= 0).any():
        k = int(np.argmax(step <= 0)) + 1
        what = "repeats" if step[k - 1] == 0 else "goes back from"
        raise TrajectoryError(
            f"row {lines[k]}: time {stamps[k]:.6f} {what} the previous row's {stamps[k - 1]:.6f}; "
            "times must increase strictly",
            p,
        )
    quat = table[:, 4:8]
    norm = np.linalg.norm(quat, axis=1)
    off = np.abs(norm - 1.0) > QUAT_NORM_TOLERANCE
    if off.any():
        k = int(np.argmax(off))
        raise TrajectoryError(
            f"row {lines[k]}: quaternion norm {norm[k]:.6f} is not 1 (tolerance {QUAT_NORM_TOLERANCE:g})", p
        )
    quat = quat / norm[:, None]
    continuous = make_quat_continuous(quat)
    n_flips = int(np.count_nonzero(np.any(continuous != quat, axis=1)))
    if n_flips:
        log.info("%s: flipped the sign of %d quaternions for continuity", p, n_flips)
    return Trajectory(stamps_s=stamps.copy(), poses=Pose(continuous, table[:, 1:4].copy()), source=str(p))


# --------------------------------------------------------------------------- writers


def _atomic_write_text(path: Path, text: str, overwrite: bool) -> None:
    from kinreg.io.atomic import atomic_path

    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_text(text, encoding="utf-8")


def format_geoslam(traj: Trajectory) -> str:
    """The GeoSLAM text of a trajectory: header plus ``t x y z q0 q1 q2 q3`` rows."""
    table = np.column_stack([traj.stamps_s, traj.poses.t_xyz, traj.poses.quat_wxyz])
    buf = io.StringIO()
    buf.write("%time x y z q0 q1 q2 q3 userfields\n")
    np.savetxt(buf, table, fmt=["%.6f"] + ["%.6f"] * 3 + ["%.9f"] * 4)
    return buf.getvalue()


def write_trajectory_geoslam(path: str | os.PathLike[str], traj: Trajectory, overwrite: bool = False) -> None:
    """Write GeoSLAM text atomically (temporary name, then rename)."""
    _atomic_write_text(Path(path), format_geoslam(traj), overwrite)


def write_trajectory_tum(path: str | Path, traj: Trajectory, overwrite: bool = False) -> None:
    """Write TUM text (``t tx ty tz qx qy qz qw``) atomically."""
    q = traj.poses.quat_wxyz
    table = np.column_stack([traj.stamps_s, traj.poses.t_xyz, q[:, 1:], q[:, :1]])
    buf = io.StringIO()
    buf.write("# timestamp tx ty tz qx qy qz qw\n")
    np.savetxt(buf, table, fmt=["%.6f"] + ["%.6f"] * 3 + ["%.9f"] * 4)
    _atomic_write_text(Path(path), buf.getvalue(), overwrite)


def write_trajectory_ply(
    path: str | Path, traj: Trajectory, binary: bool = True, overwrite: bool = False
) -> None:
    """Write a PLY trajectory (vertex: time x y z qw qx qy qz, all double) atomically."""
    from kinreg.io.atomic import atomic_path

    names = ("time", "x", "y", "z", "qw", "qx", "qy", "qz")
    table = np.column_stack([traj.stamps_s, traj.poses.t_xyz, traj.poses.quat_wxyz])
    fmt = "binary_little_endian" if binary else "ascii"
    header = "ply\nformat {} 1.0\ncomment kinreg trajectory\nelement vertex {}\n{}end_header\n".format(
        fmt, len(table), "".join(f"property double {n}\n" for n in names)
    )
    with atomic_path(Path(path), overwrite=overwrite) as tmp, open(tmp, "wb") as f:
        f.write(header.encode("ascii"))
        if binary:
            f.write(table.astype("<f8").tobytes())
        else:
            np.savetxt(f, table, fmt="%.9f")


def parse_column_mapping(text: str) -> dict[str, str | int]:
    """Parse ``time=t,x=E,y=N,...`` (values are header names or 0-based indices).

    >>> parse_column_mapping("time=gps, x=2")
    {'time': 'gps', 'x': 2}
    """
    mapping: dict[str, str | int] = {}
    for part in filter(None, (s.strip() for s in re.split(r"[,;]", text))):
        key, sep, value = part.partition("=")
        key = key.strip().lower()
        if not sep or key not in COLUMNS:
            raise TrajectoryError(f"bad column mapping '{part}': use name=column with name in {', '.join(COLUMNS)}")
        value = value.strip()
        mapping[key] = int(value) if value.isdecimal() else value  # isdigit() also takes "¹", int() does not
    return mapping


__all__ = [
    "TrajectoryFormat",
    "format_geoslam",
    "parse_column_mapping",
    "read_trajectory",
    "write_trajectory_geoslam",
    "write_trajectory_ply",
    "write_trajectory_tum",
]
