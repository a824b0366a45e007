"""The plots of ``report.html`` as inline SVG, drawn here (no plotting library, no script), and the
formatting of the report's numbers and text that the page shares with them."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from kinreg.report.text import _count, _esc, _fmt, _get, _number, _numbers
from kinreg.types import SCAN_PLANE_RANK

# Colours: trajectory before/after, the three axes and 3D, link status (colour-blind safe-ish).
GREY = "#9a9a9a"


AFTER = "#1f6fb4"


AXIS_COLOURS = {"sx_mm": "#d95f02", "sy_mm": "#1b9e77", "sz_mm": "#7570b3", "s3d_mm": "#222222"}


STATUS_COLOURS = {"ok": "#4a90c8", "prior_only": "#b0b0b0", "rejected": "#d62728"}


BLOCK_REJECTED = "#e7298a"


# Viridis, sampled at 0, 0.25, 0.5, 0.75, 1.
VIRIDIS = ((68, 1, 84), (59, 82, 139), (33, 145, 140), (94, 201, 98), (253, 231, 37))


PLOT_WIDTH = 560  # SVG units; about the CSS width of a plot in a two-column layout, so fonts are ~true size


@dataclass(frozen=True)
class _Frame:
    """A plot area in an SVG of ``width`` x ``height`` px mapping data ranges onto it."""

    width: int
    height: int
    x_range: tuple[float, float]
    y_range: tuple[float, float]
    left: int = 66
    right: int = 18
    top: int = 58
    bottom: int = 46

    @property
    def plot_w(self) -> float:
        return self.width - self.left - self.right

    @property
    def plot_h(self) -> float:
        return self.height - self.top - self.bottom

    def px(self, x: float) -> float:
        x0, x1 = self.x_range
        return self.left + (x - x0) / (x1 - x0) * self.plot_w

    def py(self, y: float) -> float:
        y0, y1 = self.y_range
        return self.top + self.plot_h - (y - y0) / (y1 - y0) * self.plot_h


def _finite(values: Iterable[Any]) -> list[float]:
    return [v for v in (_number(x) for x in values) if v is not None]


def _span(values: Iterable[Any], include_zero: bool = False) -> tuple[float, float]:
    """(min, max) of the finite values, widened where empty or degenerate."""
    v = _finite(values)
    if include_zero:
        v.append(0.0)
    if not v:
        return 0.0, 1.0
    lo, hi = min(v), max(v)
    if hi - lo < 1e-12:
        pad = max(abs(lo) * 0.05, 0.5)
        return lo - pad, hi + pad
    return lo, hi


def _nice_step(span: float, target: int = 6, min_step: float = 0.0) -> float:
    """A round step (1, 2, 2.5, 5 x 10^k) giving about ``target`` intervals over ``span``."""
    raw = max(span / max(target, 1), min_step, 1e-12)
    magnitude = 10 ** math.floor(math.log10(raw))
    for factor in (1, 2, 2.5, 5, 10):
        if factor * magnitude >= raw:
            return factor * magnitude
    return 10 * magnitude


def _ticks(lo: float, hi: float, target: int = 6, min_step: float = 0.0) -> list[float]:
    """Round tick positions within [lo, hi].

    >>> _ticks(0.0, 1.0, 5)
    [0.0, 0.2, 0.4, 0.6, 0.8, 1.0]
    """
    step = _nice_step(hi - lo, target, min_step)
    first = math.ceil(lo / step - 1e-9)
    return [round(k * step, 12) for k in range(first, math.floor(hi / step + 1e-9) + 1)]


def _nice_range(lo: float, hi: float, target: int = 6, min_step: float = 0.0) -> tuple[float, float]:
    """[lo, hi] widened outwards to whole tick steps."""
    step = _nice_step(hi - lo, target, min_step)
    return math.floor(lo / step + 1e-9) * step, math.ceil(hi / step - 1e-9) * step


def _tick_label(value: float, step: float) -> str:
    digits = max(0, -math.floor(math.log10(step) + 1e-9) + (1 if round(step / 10 ** math.floor(
        math.log10(step)), 6) == 2.5 else 0))
    text = f"{value:.{digits}f}"
    return "0" if text.strip("-0.") == "" else text


def _svg(frame: _Frame, body: Sequence[str], title: str) -> str:
    return (f'<svg viewBox="0 0 {frame.width} {frame.height}" '
            f'role="img" aria-label="{_esc(title)}" class="plot">'
            f"<title>{_esc(title)}</title>{''.join(body)}</svg>")


def _text(x: float, y: float, content: str, anchor: str = "middle", size: int = 12, cls: str = "",
          rotate: bool = False, weight: str = "") -> str:
    transform = f' transform="rotate(-90 {x:.1f} {y:.1f})"' if rotate else ""
    klass = f' class="{cls}"' if cls else ""
    bold = f' font-weight="{weight}"' if weight else ""
    return (f'<text x="{x:.1f}" y="{y:.1f}" text-anchor="{anchor}" font-size="{size}"{klass}{bold}'
            f"{transform}>{_esc(content)}</text>")


def _svg_axes(frame: _Frame, x_label: str, y_label: str, x_ticks: Sequence[float] | None = None,
              y_ticks: Sequence[float] | None = None, title: str = "") -> list[str]:
    """Frame, grid, tick labels, axis labels and the plot title."""
    x_ticks = _ticks(*frame.x_range) if x_ticks is None else x_ticks
    y_ticks = _ticks(*frame.y_range) if y_ticks is None else y_ticks
    out = [f'<rect x="{frame.left}" y="{frame.top}" width="{frame.plot_w:.1f}" height="{frame.plot_h:.1f}" '
           f'class="area"/>']
    bottom = frame.top + frame.plot_h
    x_step = x_ticks[1] - x_ticks[0] if len(x_ticks) > 1 else 1.0
    for t in x_ticks:
        x = frame.px(t)
        out.append(f'<line x1="{x:.1f}" y1="{frame.top}" x2="{x:.1f}" y2="{bottom:.1f}" class="grid"/>')
        out.append(_text(x, bottom + 17, _tick_label(t, x_step)))
    y_step = y_ticks[1] - y_ticks[0] if len(y_ticks) > 1 else 1.0
    for t in y_ticks:
        y = frame.py(t)
        out.append(f'<line x1="{frame.left}" y1="{y:.1f}" x2="{frame.left + frame.plot_w:.1f}" y2="{y:.1f}" '
                   f'class="grid"/>')
        out.append(_text(frame.left - 6, y + 4, _tick_label(t, y_step), anchor="end"))
    out.append(_text(frame.left + frame.plot_w / 2, frame.height - 8, x_label, size=13))
    out.append(_text(16, frame.top + frame.plot_h / 2, y_label, rotate=True, size=13))
    if title:
        out.append(_text(8, 17, title, anchor="start", size=14, weight="bold"))
    return out


def _polyline(frame: _Frame, xs: Sequence[Any], ys: Sequence[Any], colour: str, width: float = 1.5,
              dash: str = "", opacity: float = 1.0) -> list[str]:
    """One ``<polyline>`` per run of finite points (missing values break the line)."""
    runs: list[list[str]] = [[]]
    for x, y in zip(xs, ys, strict=False):
        fx, fy = _number(x), _number(y)
        if fx is None or fy is None:
            runs.append([])
        else:
            runs[-1].append(f"{frame.px(fx):.1f},{frame.py(fy):.1f}")
    style = f'stroke="{colour}" stroke-width="{width}" fill="none" stroke-linejoin="round"'
    style += f' stroke-dasharray="{dash}"' if dash else ""
    style += f' stroke-opacity="{opacity}"' if opacity < 1 else ""
    return [f'<polyline points="{" ".join(run)}" {style}/>' for run in runs if len(run) > 1]


def _circle(x: float, y: float, r: float, fill: str, tooltip: str = "", stroke: str = "#333") -> str:
    hover = f"<title>{_esc(tooltip)}</title>" if tooltip else ""
    return (f'<circle cx="{x:.1f}" cy="{y:.1f}" r="{r}" fill="{fill}" stroke="{stroke}" '
            f'stroke-width="0.6">{hover}</circle>')


def _legend(frame: _Frame, items: Sequence[tuple[str, str, str]]) -> list[str]:
    """A row of (label, colour, style) entries above the plot area, right-aligned;
    style is ``line``, ``dash``, ``dot`` or ``bar``."""
    widths = [30 + 6.6 * len(label) for label, _, _ in items]
    x = frame.left + frame.plot_w - sum(widths)
    y = frame.top - 30
    out = []
    for (label, colour, style), w in zip(items, widths, strict=True):
        if style == "dot":
            out.append(_circle(x + 8, y, 4, colour))
        elif style == "bar":
            out.append(f'<rect x="{x + 2:.1f}" y="{y - 5:.1f}" width="12" height="10" fill="{colour}"/>')
        else:
            dash = ' stroke-dasharray="5 3"' if style == "dash" else ""
            out.append(f'<line x1="{x:.1f}" y1="{y:.1f}" x2="{x + 18:.1f}" y2="{y:.1f}" stroke="{colour}" '
                       f'stroke-width="2.5"{dash}/>')
        out.append(_text(x + 22, y + 4, label, anchor="start"))
        x += w
    return out


def _colour_map(value: float | None, lo: float, hi: float) -> str:
    """Viridis colour of ``value`` in [lo, hi] as ``#rrggbb`` (grey for missing values).

    >>> _colour_map(0.0, 0.0, 1.0), _colour_map(1.0, 0.0, 1.0), _colour_map(None, 0.0, 1.0)
    ('#440154', '#fde725', '#bbbbbb')
    """
    if value is None:
        return "#bbbbbb"
    s = min(max((value - lo) / (hi - lo), 0.0), 1.0) if hi > lo else 0.0
    k = min(int(s * (len(VIRIDIS) - 1)), len(VIRIDIS) - 2)
    f = s * (len(VIRIDIS) - 1) - k
    rgb = [round(a + (b - a) * f) for a, b in zip(VIRIDIS[k], VIRIDIS[k + 1], strict=True)]
    return "#" + "".join(f"{c:02x}" for c in rgb)


def _colour_bar(frame: _Frame, lo: float, hi: float, label: str, ident: str) -> list[str]:
    """A vertical colour bar right of the plot area (needs ``frame.right`` >= 80)."""
    x = frame.left + frame.plot_w + 18
    top, h = frame.top, frame.plot_h
    n = len(VIRIDIS)
    stops = "".join(f'<stop offset="{k / (n - 1):.2f}" stop-color="{_colour_map(1 - k / (n - 1), 0, 1)}"/>'
                    for k in range(n))  # top of the bar is the high end
    out = [f'<defs><linearGradient id="{ident}" x1="0" y1="0" x2="0" y2="1">{stops}</linearGradient></defs>',
           f'<rect x="{x}" y="{top}" width="14" height="{h:.1f}" fill="url(#{ident})" stroke="#666" '
           f'stroke-width="0.5"/>']
    ticks = _ticks(lo, hi, 5)
    step = ticks[1] - ticks[0] if len(ticks) > 1 else 1.0
    for t in ticks:
        y = top + h - (t - lo) / (hi - lo) * h
        out.append(f'<line x1="{x + 14}" y1="{y:.1f}" x2="{x + 18}" y2="{y:.1f}" stroke="#666"/>')
        out.append(_text(x + 21, y + 4, _tick_label(t, step), anchor="start"))
    out.append(_text(x + 7, top - 10, label))
    return out


def _no_data(title: str, message: str) -> str:
    frame = _Frame(PLOT_WIDTH, 160, (0, 1), (0, 1))
    return _svg(frame, [_text(8, 17, title, anchor="start", size=14, weight="bold"),
                        _text(frame.width / 2, 90, message, cls="muted")], title)


def _equal_aspect(xs: Sequence[Any], ys: Sequence[Any], pad: float = 0.05, right: int = 18) -> _Frame:
    """A frame with data ranges covering (xs, ys) at one scale for both axes (plan views), its
    height following the data's aspect ratio within limits."""
    (x0, x1), (y0, y1) = _span(xs), _span(ys)
    probe = _Frame(PLOT_WIDTH, 0, (0, 1), (0, 1), right=right)
    aspect = (y1 - y0) / max(x1 - x0, 1e-9)
    height = round(min(max(probe.plot_w * aspect, 220), 620)) + probe.top + probe.bottom
    frame = _Frame(PLOT_WIDTH, height, (0, 1), (0, 1), right=right)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    scale = max((x1 - x0) / frame.plot_w, (y1 - y0) / frame.plot_h) * (1 + 2 * pad)  # m per px
    half_w, half_h = scale * frame.plot_w / 2, scale * frame.plot_h / 2
    return _Frame(frame.width, frame.height, (cx - half_w, cx + half_w), (cy - half_h, cy + half_h),
                  frame.left, frame.right, frame.top, frame.bottom)


def _offset(values: Iterable[Any]) -> float:
    """A round offset to subtract from large coordinates (UTM) so tick labels stay short."""
    lo, hi = _span(values)
    centre = (lo + hi) / 2
    return 0.0 if abs(centre) < 1e4 else round(centre, -3)


def _axis_name(name: str, offset: float, unit: str = "m") -> str:
    return f"{name} \u2212 {offset:.0f} [{unit}]" if offset else f"{name} [{unit}]"


def _shift(values: Sequence[Any], offset: float) -> list[float | None]:
    return [None if v is None else v - offset for v in _numbers(list(values))]


def _rows(report: dict[str, Any]) -> list[dict[str, Any]]:
    rows = _get(report, "stations", "rows", default=[])
    return [r for r in rows if isinstance(r, dict)] if isinstance(rows, list) else []


def _time_origin(rows: Sequence[dict[str, Any]]) -> float | None:
    """Station times are absolute (GPS/Unix); ``trajectory_plot.t`` starts at the trajectory start,
    which is where the first window starts."""
    starts = _finite(r.get("t_start") for r in rows) or _finite(r.get("t") for r in rows)
    return min(starts) if starts else None


def _time_unit(duration_s: float) -> tuple[float, str]:
    return (1.0, "s") if duration_s <= 900 else (1 / 60, "min")


def _station_times(rows: Sequence[dict[str, Any]]) -> list[float | None]:
    t0 = _time_origin(rows)
    return [None if (t := _number(r.get("t"))) is None or t0 is None else t - t0 for r in rows]


def _plot_plan(report: dict[str, Any]) -> str:
    """Trajectory before (grey) and after (colour) in plan, stations coloured by sigma 3D."""
    title = "Plan view: trajectory before and after, stations by position \u03c3"
    traj = _get(report, "trajectory_plot", default={})
    rows = _rows(report)
    xs_all = _numbers(traj.get("x_before", [])) + _numbers(traj.get("x_after", [])) + [_number(r.get("x"))
                                                                                         for r in rows]
    ys_all = _numbers(traj.get("y_before", [])) + _numbers(traj.get("y_after", [])) + [_number(r.get("y"))
                                                                                         for r in rows]
    if not _finite(xs_all) or not _finite(ys_all):
        return _no_data(title, "no trajectory or station positions in the report")
    ox, oy = _offset(xs_all), _offset(ys_all)
    frame = _equal_aspect(_shift(xs_all, ox), _shift(ys_all, oy), right=90)
    s3d = [_number(r.get("s3d_mm")) for r in rows]
    lo, hi = _nice_range(0.0, max(_finite(s3d), default=1.0) or 1.0, 5)
    body = _svg_axes(frame, _axis_name("x", ox), _axis_name("y", oy), title=title)
    body += _polyline(frame, _shift(traj.get("x_before", []), ox), _shift(traj.get("y_before", []), oy), GREY,
                      1.4)
    body += _polyline(frame, _shift(traj.get("x_after", []), ox), _shift(traj.get("y_after", []), oy), AFTER,
                      1.6)
    for row, s in zip(rows, s3d, strict=True):
        x, y = _number(row.get("x")), _number(row.get("y"))
        if x is not None and y is not None:
            tip = f"{row.get('station', '')}: \u03c33D = {_fmt(s, 2, 'mm')}" + (" (fixed)" if row.get("fixed")
                                                                                  else "")
            body.append(_circle(frame.px(x - ox), frame.py(y - oy), 5.5 if row.get("fixed") else 4.5,
                                _colour_map(s, lo, hi), tip, stroke="#000" if row.get("fixed") else "#333"))
    body += _colour_bar(frame, lo, hi, "\u03c33D [mm]", "cbar-plan")
    body += _legend(frame, [("before", GREY, "line"), ("after", AFTER, "line"), ("station", _colour_map(
        hi / 2, lo, hi), "dot")])
    return _svg(frame, body, title)


def _plot_sigma_time(report: dict[str, Any]) -> str:
    """Position standard deviations of the stations along time."""
    title = "Position \u03c3 of the stations along time"
    rows = _rows(report)
    t = _station_times(rows)
    keys = ("sx_mm", "sy_mm", "sz_mm", "s3d_mm")
    values = [_number(r.get(k)) for r in rows for k in keys]
    if not _finite(t) or not _finite(values):
        return _no_data(title, "no station times or sigmas in the report")
    factor, unit = _time_unit(max(_finite(t)))
    ts = [None if v is None else v * factor for v in t]
    frame = _Frame(PLOT_WIDTH, 330, _nice_range(*_span(ts, include_zero=True)),
                   _nice_range(*_span(values, True), 5))
    body = _svg_axes(frame, f"time since start [{unit}]", "\u03c3 [mm]", title=title)
    for key in keys:
        width = 2.4 if key == "s3d_mm" else 1.4
        body += _polyline(frame, ts, [r.get(key) for r in rows], AXIS_COLOURS[key], width)
    for row, x in zip(rows, ts, strict=True):
        y = _number(row.get("s3d_mm"))
        if x is not None and y is not None:
            body.append(_circle(frame.px(x), frame.py(y), 2.6, AXIS_COLOURS["s3d_mm"],
                                f"{row.get('station', '')}: \u03c3x {_fmt(row.get('sx_mm'), 2)}, "
                                f"\u03c3y {_fmt(row.get('sy_mm'), 2)}, \u03c3z {_fmt(row.get('sz_mm'), 2)}, "
                                f"\u03c33D {_fmt(y, 2)} mm"))
    body += _legend(frame, [(label, AXIS_COLOURS[key], "line") for label, key in (
        ("\u03c3x", "sx_mm"), ("\u03c3y", "sy_mm"), ("\u03c3z", "sz_mm"), ("\u03c33D", "s3d_mm"))])
    return _svg(frame, body, title)


def _station_gaps(report: dict[str, Any], rows: Sequence[dict[str, Any]]) -> list[float | None]:
    """The rigid-fit gap of every station (None where it has none): the gaps are listed for the
    quasi-static stations in station order."""
    gaps = _numbers(_get(report, "before_after", "gap_per_station_mm", default=[]))
    quasi = [k for k, r in enumerate(rows) if r.get("kind", "quasi_static") == "quasi_static"]
    out: list[float | None] = [None] * len(rows)
    if len(gaps) == len(quasi):
        for k, g in zip(quasi, gaps, strict=True):
            out[k] = g
    elif len(gaps) == len(rows):
        out = gaps
    return out


def _plot_correction(report: dict[str, Any]) -> str:
    """Horizontal shift of the trajectory (after - before) along time and the stations' gaps."""
    title = "Correction along time and residual gaps of the stations"
    traj = _get(report, "trajectory_plot", default={})
    rows = _rows(report)
    t = _numbers(traj.get("t", []))
    cols = [_numbers(traj.get(k, [])) for k in ("x_before", "y_before", "x_after", "y_after")]
    shift: list[float | None] = []
    for k in range(len(t)):
        xb, yb, xa, ya = (c[k] if k < len(c) else None for c in cols)
        if xb is None or yb is None or xa is None or ya is None:
            shift.append(None)
        else:
            shift.append(math.hypot(xa - xb, ya - yb) * 1000.0)
    st = _station_times(rows)
    gaps = _station_gaps(report, rows)
    if not _finite(shift) and not _finite(gaps):
        return _no_data(title, "no trajectory or gaps in the report")
    factor, unit = _time_unit(max(_finite(t) + _finite(st), default=1.0))
    t = [None if v is None else v * factor for v in t]
    st = [None if v is None else v * factor for v in st]
    frame = _Frame(PLOT_WIDTH, 330, _nice_range(*_span(t + st, include_zero=True)),
                   _nice_range(*_span(shift + gaps, include_zero=True), 5))
    body = _svg_axes(frame, f"time since start [{unit}]", "distance [mm]", title=title)
    body += _polyline(frame, t, shift, AFTER, 1.6)
    for row, x, g in zip(rows, st, gaps, strict=True):
        if x is not None and g is not None:
            body.append(_circle(frame.px(x), frame.py(g), 3.2, "#f28e2b",
                                f"{row.get('station', '')}: gap {_fmt(g, 2, 'mm')}"))
    body += _legend(frame, [("horizontal shift after \u2212 before", AFTER, "line"),
                            ("station gap after rigid fit", "#f28e2b", "dot")])
    return _svg(frame, body, title)


def _block_rejected_pairs(report: dict[str, Any]) -> set[tuple[int, int]]:
    out = set()
    for obs in _get(report, "adjustment", "rejected_observations", default=[]) or []:
        if isinstance(obs, dict) and isinstance(obs.get("i"), int) and isinstance(obs.get("j"), int):
            out.add((min(obs["i"], obs["j"]), max(obs["i"], obs["j"])))
    return out


def _plot_links(report: dict[str, Any]) -> str:
    """The link graph in plan: stations at their positions, links coloured by status."""
    title = "Link graph: pairwise links between the stations"
    rows = _rows(report)
    xs, ys = [_number(r.get("x")) for r in rows], [_number(r.get("y")) for r in rows]
    if not _finite(xs) or not _finite(ys):
        return _no_data(title, "no station positions in the report")
    ox, oy = _offset(xs), _offset(ys)
    xs, ys = _shift(xs, ox), _shift(ys, oy)
    frame = _equal_aspect(xs, ys, pad=0.08)
    body = _svg_axes(frame, _axis_name("x", ox), _axis_name("y", oy), title=title)
    rejected_in_block = _block_rejected_pairs(report)
    pairs = _get(report, "links", "pairs", default=[]) or []
    highlighted = []
    order = {"prior_only": 0, "ok": 1, "rejected": 2}  # draw the important ones last
    valid = [p for p in pairs if isinstance(p, list | tuple) and len(p) >= 2]
    for p in sorted(valid, key=lambda p: order.get(str(p[2]) if len(p) > 2 else "ok", 1)):
        i, j, status = p[0], p[1], str(p[2]) if len(p) > 2 else "ok"
        if not (isinstance(i, int) and isinstance(j, int) and 0 <= i < len(rows) and 0 <= j < len(rows)):
            continue
        xi, yi, xj, yj = xs[i], ys[i], xs[j], ys[j]
        if xi is None or yi is None or xj is None or yj is None:
            continue
        x1, y1, x2, y2 = frame.px(xi), frame.py(yi), frame.px(xj), frame.py(yj)
        style = {"prior_only": ' stroke-dasharray="4 3"', "rejected": ' stroke-width="1.8"'}.get(status, "")
        tip = f"{rows[i].get('station', i)} \u2013 {rows[j].get('station', j)}: {status}"
        body.append(f'<line x1="{x1:.1f}" y1="{y1:.1f}" x2="{x2:.1f}" y2="{y2:.1f}" '
                    f'stroke="{STATUS_COLOURS.get(status, "#555")}" stroke-opacity="0.75"{style}>'
                    f"<title>{_esc(tip)}</title></line>")
        if (min(i, j), max(i, j)) in rejected_in_block:
            highlighted.append(f'<line x1="{x1:.1f}" y1="{y1:.1f}" x2="{x2:.1f}" y2="{y2:.1f}" '
                               f'stroke="{BLOCK_REJECTED}" stroke-width="3.5" stroke-opacity="0.85">'
                               f"<title>{_esc(tip)}, rejected in the block adjustment</title></line>")
    body += highlighted
    for row, x, y in zip(rows, xs, ys, strict=True):
        if x is not None and y is not None:
            tip = (f"{row.get('station', '')}: {_count(row.get('n_links'))} links, "
                   f"{_count(row.get('n_planes'))} planes")
            fill = "#ffffff" if row.get("kind") == "static" else "#333333"
            body.append(_circle(frame.px(x), frame.py(y), 5 if row.get("fixed") else 3, fill, tip))
    items = [(name, STATUS_COLOURS[key], "dash" if key == "prior_only" else "line")
             for key, name in (("ok", "ok"), ("prior_only", "prior only"), ("rejected", "rejected"))]
    items.append(("rejected in block", BLOCK_REJECTED, "line"))
    body += _legend(frame, items)
    return _svg(frame, body, title)


def _reference_density(y: float, dofs: dict[int, float]) -> float:
    """Density of sqrt(chi2_k / k), mixed over ``dofs`` {k: weight}: the normalised residual
    sqrt(statistic / dof) of an observation whose a-priori model is right (sigma0 = 1)."""
    total = sum(dofs.values())
    out = 0.0
    for k, w in dofs.items():
        x = k * y * y
        log_chi2 = (k / 2 - 1) * math.log(x) - x / 2 - k / 2 * math.log(2) - math.lgamma(k / 2)
        out += w / total * 2 * k * y * math.exp(log_chi2)
    return out


def _normal_density(y: float) -> float:
    return math.exp(-y * y / 2) / math.sqrt(2 * math.pi)


_SCAN_PLANE_DOF = {kind.value: rank for kind, rank in SCAN_PLANE_RANK.items()}


def _residual_dofs(report: dict[str, Any], kind: str) -> dict[int, float]:
    """Degrees of freedom per observation kind: plane links have the rank of their plane set, a
    scan plane's tilts 2 and its offset 1 (:mod:`kinreg.estimate.plane_nodes`), trajectory and
    station observations are full 6-dof poses."""
    if kind in _SCAN_PLANE_DOF:
        return {_SCAN_PLANE_DOF[kind]: 1.0}
    if kind == "planes":
        hist = _get(report, "links", "rank_histogram", default={}) or {}
        dofs = {int(k): float(v) for k, v in hist.items() if str(k).isdigit() and 0 < int(k) <= 6
                and _number(v)}
        if dofs:
            return dofs
    return {6: 1.0}


def _plot_histogram(report: dict[str, Any], kind: str, values: Sequence[Any]) -> str:
    """Histogram of the normalised residuals of one observation kind with the expected curve."""
    v = _finite(values)
    title = f"Normalised residuals: {kind}"
    if not v:
        return _no_data(title, "no residuals")
    signed = min(v) < 0
    ordered = sorted(abs(x) for x in v)
    top = max(3.0, min(ordered[int(0.99 * (len(ordered) - 1))] * 1.1, 8.0))
    bin_w = _nice_step(2 * top if signed else top, 30)
    n_bins = math.ceil(top / bin_w)
    lo = -n_bins * bin_w if signed else 0.0
    hi = n_bins * bin_w
    counts = [0] * (2 * n_bins if signed else n_bins)
    for x in v:
        counts[min(max(int((x - lo) / bin_w), 0), len(counts) - 1)] += 1  # overflow into the end bins
    grid = [lo + (hi - lo) * (k + 0.5) / 200 for k in range(200)]
    dofs = _residual_dofs(report, kind)
    density = [_normal_density(y) if signed else _reference_density(y, dofs) for y in grid]
    expected = [len(v) * bin_w * d for d in density]
    y_range = _nice_range(0.0, max(max(counts), max(expected)) * 1.05, 5, min_step=1.0)
    frame = _Frame(PLOT_WIDTH, 300, (lo, hi), y_range)
    rms = math.sqrt(sum(x * x for x in v) / len(v))
    body = _svg_axes(frame, "normalised residual", "count", y_ticks=_ticks(*y_range, 5, min_step=1.0),
                     title=f"{kind}: n = {len(v)}, RMS {rms:.2f}")
    for k, c in enumerate(counts):
        if c:
            x0, x1 = frame.px(lo + k * bin_w), frame.px(lo + (k + 1) * bin_w)
            body.append(f'<rect x="{x0:.1f}" y="{frame.py(c):.1f}" width="{max(x1 - x0 - 1, 0.5):.1f}" '
                        f'height="{frame.py(0) - frame.py(c):.1f}" fill="#7fa7cf">'
                        f"<title>{c} in [{lo + k * bin_w:.2f}, {lo + (k + 1) * bin_w:.2f})</title></rect>")
    body += _polyline(frame, grid, expected, "#c0392b", 2.0)
    reference = "N(0,1)" if signed else "if \u03c30 = 1"
    body += _legend(frame, [("observed", "#7fa7cf", "bar"), (f"expected {reference}", "#c0392b", "line")])
    return _svg(frame, body, title)


def _plot_histograms(report: dict[str, Any]) -> list[str]:
    residuals = _get(report, "adjustment", "normalised_residuals", default={})
    if not isinstance(residuals, dict) or not residuals:
        return [_no_data("Normalised residuals", "no normalised residuals in the report")]
    return [_plot_histogram(report, str(kind), values if isinstance(values, list) else [])
            for kind, values in residuals.items()]
