"""Reading control and check points: surveyed coordinates of points the unit stood on (CSV).

One row per point, comma separated, with a header naming the columns (in any order)::

    name,x,y,z,sigma_mm
    CP01,512306.1904,5402105.6168,312.3069,3
    CP02,512301.2919,5402104.2156,312.3195,3

``x, y, z`` are object-frame coordinates [m] of the point on the ground (or wherever the unit's
reference point ``[control] reference_point_m`` touched it); ``sigma_mm`` its standard deviation per
axis. Optional ``t_start,t_end`` [s, the trajectory's time base] give the interval the unit stood
on the point; without them kinreg finds the stand-stills in the trajectory itself
(:mod:`kinreg.estimate.control`). The same format serves check points (``--check``), which are
only compared, never adjusted. Empty lines and lines starting with ``#`` are skipped.

**Targets in static scans.** A row may instead name a target that a static scan (``--static``)
measured: ``station`` names the scan and ``sx, sy, sz`` [m] are the target's coordinates in that
scan's own frame (the frame of its points in the E57 file, before its pose)::

    name,x,y,z,sigma_mm,station,sx,sy,sz
    CP01,512306.1904,5402105.6168,312.3069,3,,,,
    T01,512310.0021,5402101.3310,313.8214,2,static_00,4.1832,-2.0117,0.4121

``station`` is the scan's ``name`` in the E57 file (as ``stations.csv`` lists it; a scan without
a name is ``static_000``, ``static_001``, ... by its position), or else its 0-based position in
the file. Rows with an empty ``station`` are stand-still points as above; one file may mix both.
A target row leaves ``t_start,t_end`` empty. The reader checks the rows; which scans exist is
checked against the E57 file (:func:`kinreg.estimate.control.assign_points`).

Every problem raises :class:`~kinreg.errors.InputError` with the file path and one line.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from kinreg.errors import InputError
from kinreg.geometry import FloatArray

# The file's content as the estimation takes it; importable from here as well (redundant aliases:
# re-exported).
from kinreg.survey import ControlPoint as ControlPoint
from kinreg.survey import ControlPoints as ControlPoints

REQUIRED_COLUMNS = ("name", "x", "y", "z", "sigma_mm")
TIME_COLUMNS = ("t_start", "t_end")
TARGET_COLUMNS = ("station", "sx", "sy", "sz")


def read_control_points(path: str | Path) -> ControlPoints:
    """The points of a control or check file (see the module's docstring). Raises
    :class:`InputError` naming the file for a missing file or column, a value that is not a finite
    number, a sigma that is not positive, a duplicate name, an interval with one time only or
    ending before it starts, a target row without all of ``sx, sy, sz`` (or with times), or a file
    without points."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputError("control file not found", path) from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"cannot read the control file ({e})", path) from None
    return parse_control_points(text, str(path))


def parse_control_points(text: str, source: str) -> ControlPoints:
    """:func:`read_control_points` of the file's ``text``."""
    lines = [line for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")]
    if not lines:
        raise InputError("the control file is empty (expected a header 'name,x,y,z,sigma_mm' and one row per point)",
                         source)
    rows = list(csv.reader(lines))
    header = [h.strip().lower() for h in rows[0]]
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise InputError(f"missing column(s) {', '.join(missing)} in the header (expected name,x,y,z,sigma_mm "
                         "and optionally t_start,t_end and station,sx,sy,sz)", source)
    if len(set(header)) != len(header):
        raise InputError("a column is named twice in the header", source)
    has_times = [c for c in TIME_COLUMNS if c in header]
    if len(has_times) == 1:
        raise InputError(f"column {has_times[0]} without {({'t_start', 't_end'} - set(has_times)).pop()}: give both "
                         "or neither", source)
    has_targets = [c for c in TARGET_COLUMNS if c in header]
    if has_targets and len(has_targets) < len(TARGET_COLUMNS):
        absent = ", ".join(c for c in TARGET_COLUMNS if c not in header)
        raise InputError(f"column(s) {', '.join(has_targets)} without {absent}: a target in a static scan needs "
                         "station,sx,sy,sz", source)
    col = {name: header.index(name) for name in header}
    points: list[ControlPoint] = []
    seen: set[str] = set()
    for line_no, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise InputError(f"line {line_no}: {len(row)} values for {len(header)} columns", source)
        name = row[col["name"]].strip()
        if not name:
            raise InputError(f"line {line_no}: the point has no name", source)
        if name in seen:
            raise InputError(f"line {line_no}: point {name} is given twice", source)
        seen.add(name)
        values = {c: _number(row[col[c]], c, name, line_no, source) for c in ("x", "y", "z", "sigma_mm")}
        if not values["sigma_mm"] > 0:
            raise InputError(f"line {line_no}: point {name}: sigma_mm must be positive, got {values['sigma_mm']:g}",
                             source)
        t_start = t_end = math.nan
        station = row[col["station"]].strip() if has_targets else ""
        scan_xyz: FloatArray | None = None
        if has_targets and (station or any(row[col[c]].strip() for c in ("sx", "sy", "sz"))):
            if not station:
                raise InputError(f"line {line_no}: point {name}: sx,sy,sz given without a station (the static scan "
                                 "that measured the target)", source)
            empty = [c for c in ("sx", "sy", "sz") if not row[col[c]].strip()]
            if empty:
                raise InputError(f"line {line_no}: target {name} in static scan {station}: {', '.join(empty)} "
                                 "missing (its coordinates in the scan's frame)", source)
            scan_xyz = np.array([_number(row[col[c]], c, name, line_no, source) for c in ("sx", "sy", "sz")])
            if has_times and any(row[col[c]].strip() for c in TIME_COLUMNS):
                raise InputError(f"line {line_no}: target {name} in static scan {station}: leave t_start,t_end empty "
                                 "(the unit does not stand on a target in a static scan)", source)
        elif has_times:
            t_start, t_end = (_number(row[col[c]], c, name, line_no, source) for c in TIME_COLUMNS)
            if not t_end > t_start:
                raise InputError(f"line {line_no}: point {name}: t_end ({t_end:.3f}) is not after t_start "
                                 f"({t_start:.3f})", source)
        points.append(ControlPoint(name, np.array([values["x"], values["y"], values["z"]]),
                                   values["sigma_mm"] / 1000.0, t_start, t_end, station, scan_xyz, line_no))
    if not points:
        raise InputError("the control file has a header but no points", source)
    return ControlPoints(tuple(points), source)


def _number(text: str, column: str, name: str, line_no: int, source: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"line {line_no}: point {name}: {column} is not a number ({text.strip()!r})",
                         source) from None
    if not math.isfinite(value):
        raise InputError(f"line {line_no}: point {name}: {column} is not a finite number ({text.strip()})",
                         source)
    return value
