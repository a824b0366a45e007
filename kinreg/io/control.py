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

Every problem raises :class:`~kinreg.errors.InputError` with the file path and one line.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kinreg.errors import InputError
from kinreg.geometry import FloatArray

REQUIRED_COLUMNS = ("name", "x", "y", "z", "sigma_mm")
TIME_COLUMNS = ("t_start", "t_end")


@dataclass(frozen=True, eq=False)
class ControlPoint:
    """One surveyed point: its name, object-frame coordinates [m], standard deviation per axis
    [m], and the interval [s] the unit stood on it (``nan``: to be found in the trajectory)."""

    name: str
    xyz: FloatArray
    sigma_m: float
    t_start_s: float = math.nan
    t_end_s: float = math.nan

    @property
    def has_times(self) -> bool:
        return math.isfinite(self.t_start_s)


@dataclass(frozen=True, eq=False)
class ControlPoints:
    """The points of one file, in file order; ``source`` is the file (for messages)."""

    points: tuple[ControlPoint, ...]
    source: str

    def __len__(self) -> int:
        return len(self.points)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.points)


def read_control_points(path: str | Path) -> ControlPoints:
    """The points of a control or check file (see the module's docstring). Raises
    :class:`InputError` naming the file for a missing file or column, a value that is not a finite
    number, a sigma that is not positive, a duplicate name, an interval with one time only or
    ending before it starts, or a file without points."""
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
                         "and optionally t_start,t_end)", source)
    if len(set(header)) != len(header):
        raise InputError("a column is named twice in the header", source)
    has_times = [c for c in TIME_COLUMNS if c in header]
    if len(has_times) == 1:
        raise InputError(f"column {has_times[0]} without {({'t_start', 't_end'} - set(has_times)).pop()}: give both "
                         "or neither", source)
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
        if has_times:
            t_start, t_end = (_number(row[col[c]], c, name, line_no, source) for c in TIME_COLUMNS)
            if not t_end > t_start:
                raise InputError(f"line {line_no}: point {name}: t_end ({t_end:.3f}) is not after t_start "
                                 f"({t_start:.3f})", source)
        points.append(ControlPoint(name, np.array([values["x"], values["y"], values["z"]]),
                                   values["sigma_mm"] / 1000.0, t_start, t_end))
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
