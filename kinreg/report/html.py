"""Self-contained HTML accuracy report (METHOD.md section 2 step 10, section 6: ``report.html``).

:func:`render_html` turns the ``report.json`` dictionary into one HTML page that needs nothing
else: inline CSS, plots as inline SVG drawn here (no plotting library, no script, no network).
The page shows the inputs, a verdict line, the key figures in the form the seed paper reports
them (position sigma RMS/max, gaps before/after mean/max), five kinds of plot, the station table
and the resolved configuration.

The input may be the cleaned JSON (NaN written as ``null``) or the dictionary straight from
:func:`kinreg.report.json.build_report` (numpy scalars and arrays, NaN floats); any key may be missing.

Bump :data:`REPORT_HTML_VERSION` when the page's layout or content changes in a way a reader of
old reports should know about.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from kinreg.report.cloud_html import cloud_section, thickness_figure
from kinreg.report.control import control_html
from kinreg.report.plots import _plot_correction, _plot_histograms, _plot_links, _plot_plan, _plot_sigma_time, _rows
from kinreg.report.text import DASH, _count, _duration, _esc, _fmt, _get, _number, _numbers, _plain, _tag

REPORT_HTML_VERSION = 2  # 2: the cloud (sections, plane thickness), the CRS, phone and print layout


STATION_COLUMNS = ("station", "t", "t_start", "t_end", "x", "y", "z", "qw", "qx", "qy", "qz", "sx_mm",
                   "sy_mm", "sz_mm", "s3d_mm", "n_points", "n_planes", "n_links", "srx_mdeg", "sry_mdeg",
                   "srz_mdeg", "kind", "fixed")
COLUMN_DIGITS = {"t": 3, "t_start": 3, "t_end": 3, "x": 4, "y": 4, "z": 4, "qw": 6, "qx": 6, "qy": 6, "qz": 6,
                 "sx_mm": 2, "sy_mm": 2, "sz_mm": 2, "s3d_mm": 2, "srx_mdeg": 1, "sry_mdeg": 1, "srz_mdeg": 1}






# --------------------------------------------------------------------------------------------
# Page sections
# --------------------------------------------------------------------------------------------

CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,"DejaVu Sans",sans-serif;margin:0;color:#222;
background:#f6f7f9;line-height:1.4}
main{max-width:1380px;margin:0 auto;padding:18px 24px 40px}
h1{font-size:1.5em;margin:.2em 0}
h2{font-size:1.15em;margin:1.4em 0 .5em;border-bottom:1px solid #ddd;padding-bottom:.2em}
.sub{color:#666;font-size:.9em}
.verdict{padding:10px 14px;border-radius:6px;font-size:1.1em;margin:12px 0;border-left:6px solid}
.verdict.pass{background:#e8f5e9;border-color:#2e7d32}
.verdict.warn{background:#fff8e1;border-color:#f9a825}
.verdict.fail{background:#ffebee;border-color:#c62828}
.cards{display:grid;grid-template-columns:repeat(auto-fit,minmax(min(540px,100%),1fr));gap:16px;align-items:start}
.card h3{margin:.1em 0 .4em;font-size:1.05em}
.card td:first-child,.figures td{white-space:nowrap}
.inputs td+td{word-break:break-all}
.figures td{font-size:1.1em}
.card{background:#fff;border:1px solid #e0e0e0;border-radius:6px;padding:10px 14px;min-width:0;overflow-x:auto}
table{border-collapse:collapse;font-size:.92em}
td,th{padding:3px 10px;text-align:left;vertical-align:top}
td.num,th.num{text-align:right;font-variant-numeric:tabular-nums}
tr+tr td{border-top:1px solid #eee}
th{color:#555;font-weight:600}
.bar{display:inline-block;height:9px;background:#1f6fb4;border-radius:2px;vertical-align:middle}
.plots{display:grid;grid-template-columns:repeat(auto-fit,minmax(min(560px,100%),1fr));gap:16px}
figure{margin:0;background:#fff;border:1px solid #e0e0e0;border-radius:6px;padding:8px}
figcaption{color:#555;font-size:.85em;padding:4px 6px}
svg.plot{width:100%;height:auto;display:block;font-family:inherit}
svg .area{fill:#fff;stroke:#999;stroke-width:1}
svg .grid{stroke:#e6e6e6;stroke-width:1}
svg text{fill:#333}
svg .muted{fill:#888}
details{background:#fff;border:1px solid #e0e0e0;border-radius:6px;padding:8px 12px;margin:10px 0}
summary{cursor:pointer;font-weight:600}
.scroll{overflow-x:auto;max-height:640px}
.stations td{white-space:nowrap}
.stations tr.fixed td{background:#eef4fb}
pre{background:#fafafa;border:1px solid #eee;padding:10px;overflow-x:auto;font-size:.85em}
footer{color:#888;font-size:.8em;margin-top:2em}
figure{margin-bottom:16px;min-width:0}
.pair{display:grid;grid-template-columns:repeat(auto-fit,minmax(min(420px,100%),1fr));gap:8px}
.insets{display:grid;grid-template-columns:repeat(auto-fit,minmax(min(400px,100%),1fr));gap:12px}
.insets .pair{grid-template-columns:1fr 1fr}
img.cloud{width:100%;height:auto;display:block;border:1px solid #eee;image-rendering:auto}
@media (max-width:640px){main{padding:10px 8px 30px}.card{padding:8px}td,th{padding:3px 5px}
.figures td{white-space:normal;font-size:1em}.card td:first-child{white-space:normal}}
@page{size:A4;margin:12mm}
@media print{body{background:#fff;font-size:10pt}main{max-width:none;padding:0}
.cards,.plots{grid-template-columns:1fr 1fr}.pair{grid-template-columns:1fr 1fr}
.card,figure,details,.verdict{break-inside:avoid}.scroll{max-height:none;overflow:visible}
.card{overflow:visible}.stations{font-size:7pt}}
"""


def _table(rows: Sequence[tuple[str, ...]], header: Sequence[str] = (), numeric_from: int = 1,
           cls: str = "") -> str:
    """A small table; cells are escaped, columns from ``numeric_from`` on are right-aligned."""
    def cell(k: int, text: str, tag: str = "td") -> str:
        return _tag(tag, _esc(text), class_="num" if k >= numeric_from else None)
    head = _tag("tr", "".join(cell(k, h, "th") for k, h in enumerate(header))) if header else ""
    body = "".join(_tag("tr", "".join(cell(k, c) for k, c in enumerate(r))) for r in rows)
    return _tag("table", head + body, class_=cls or None)


def _section_inputs(report: dict[str, Any]) -> str:
    inputs = _get(report, "inputs", default={})
    slicing = _get(report, "slicing", default={})
    runs = [r for r in _get(report, "inputs", "runs", default=[]) if isinstance(r, dict)]
    if len(runs) > 1:  # several runs in one project: the files of each, then the totals
        files = [(f"run {k} {key}", str(r.get(key) or DASH)) for k, r in enumerate(runs, 1)
                 for key in ("trajectory", "cloud")]
    else:
        files = [("trajectory", str(inputs.get("trajectory") or DASH)), ("cloud", str(inputs.get("cloud") or DASH))]
    rows = [
        *files,
        ("points", _count(inputs.get("n_points"))),
        ("trajectory rows", _count(inputs.get("n_trajectory_rows"))),
        ("duration", _duration(inputs.get("duration_s"))),
        ("path length", _fmt(inputs.get("path_length_m"), 1, "m")),
        ("quasi-static scans", _count(slicing.get("n_scans"))),
        ("window", _window_text(slicing)),
        ("skipped windows", _count(len(slicing.get("skipped_windows") or []))),
        ("points outside trajectory", _count(slicing.get("n_points_outside_trajectory"))),
        ("coordinate system", _crs_text(_get(report, "crs", default={}))),
    ]
    return _tag("div", "<h3>Inputs</h3>" + _table(rows, numeric_from=9, cls="inputs"), class_="card")


def _crs_text(crs: Any) -> str:
    if not isinstance(crs, dict) or not crs:
        return "not declared"
    epsg = crs.get("epsg")
    return f"{crs.get('name') or DASH}" + (f" (EPSG:{epsg})" if epsg else "")


def _window_text(slicing: dict[str, Any]) -> str:
    """The window length, the first one where the drift made kinreg slice again, whether the
    windows' points were deskewed before their planes were detected, and the smear."""
    text = _fmt(slicing.get("window_s"), 1, "s")
    if slicing.get("window_s_first") is not None:
        text += f" (sliced again: {_fmt(slicing.get('window_s_first'), 1, 's')} smeared the planes)"
    if slicing.get("points_deskewed"):
        text += ", points deskewed"  # the attitude error sheared the windows
    smear = (slicing.get("smear_mm") or {}).get("median")
    return text if smear is None else f"{text}, drift over half a window {_fmt(smear, 1, 'mm')}"


def _verdict(report: dict[str, Any]) -> str:
    adj = _get(report, "adjustment", default={})
    passed = adj.get("global_test_passed")
    rejected = adj.get("rejected_observations") or []
    n_obs = adj.get("n_observations")
    if adj.get("status") == "failed":
        return _tag("div", _esc(f"ADJUSTMENT FAILED: {adj.get('failure') or DASH}. This run has no result: "
                                "no station, link or correction of it may be used."), class_="verdict fail")
    misfits = adj.get("trajectory_misfits") or []
    test = {True: "global test passed", False: "global test FAILED"}.get(passed, "global test not available")
    level = "fail" if passed is False else ("warn" if rejected or misfits or passed is None else "pass")
    text = (f"\u03c3\u2080 = {_fmt(adj.get('sigma0'), 3)} \u2014 {test} (\u03b1 = {adj.get('alpha', DASH)}, "
            f"redundancy {_fmt(adj.get('redundancy'), 0)}) \u00b7 {len(rejected)} of {_count(n_obs)} "
            f"observations rejected \u00b7 datum: {adj.get('datum', DASH)}")
    if misfits:
        worst = ", ".join(f"{m['stations'][0]}-{m['stations'][1]} ({_fmt(m['normalised'], 0)} \u03c3"
                          + (f", {_fmt(m['moved_mm'], 1)} mm)" if m.get("moved_mm") is not None else ")")
                          for m in misfits[:5])
        text += (f" \u00b7 the trajectory disagrees with the network between {len(misfits)} pair(s) of "
                 f"consecutive stations, {worst}, by less than a wrong plane match would: the stations there "
                 "may be less accurate than their sigmas say")
    return _tag("div", _esc(text), class_=f"verdict {level}")


def _key_figures(report: dict[str, Any]) -> str:
    st, ba = _get(report, "stations", default={}), _get(report, "before_after", default={})
    pos, rot = st.get("position_sigma_mm") or {}, st.get("orientation_sigma_mdeg") or {}
    gaps, corr = ba.get("gaps_mm") or {}, st.get("correction_mm") or {}
    corr_rot = st.get("correction_mdeg") or {}

    def figure(label: str, stats: dict[str, Any], first: str, unit: str) -> tuple[str, str, str]:
        value, largest = _fmt(stats.get(first.lower()), 1, unit), _fmt(stats.get("max"), 1, unit)
        return label, f"{first} {value}", f"max {largest}"

    rows = [
        figure("position \u03c3 (3D)", pos, "RMS", "mm"),
        figure("orientation \u03c3", rot, "RMS", "mdeg"),
        figure("gaps before/after", gaps, "mean", "mm"),
        figure("correction", corr, "mean", "mm"),
        figure("correction (rotation)", corr_rot, "mean", "mdeg"),
    ]
    if _get(report, "cloud", "thickness", default=None):
        rows.append(thickness_figure(report))
    table = _table(rows, numeric_from=1, cls="figures")
    note = ("<p class='sub'>Gaps: station positions before vs after networking, after a rigid 3D "
            f"transformation (rotation {_esc(_fmt(ba.get('rotation_mdeg'), 1, 'mdeg'))}). Stations: "
            f"{_esc(_count(st.get('n')))}, fixed {_esc(_count(st.get('n_fixed')))}. Seed paper, sequence "
            "only: \u03c3 RMS 4.2 / max 12 mm, gaps mean 10 / max 30 mm.</p>")
    return _tag("div", "<h3>Key figures</h3>" + table + note, class_="card")


def _drift_and_links(report: dict[str, Any]) -> str:
    adj, links = _get(report, "adjustment", default={}), _get(report, "links", default={})
    rates = adj.get("drift_rates") or {}
    pos, rot = _numbers(rates.get("pos_mm_per_s") or []), _numbers(rates.get("rot_mdeg_per_s") or [])
    estimated = rates.get("estimated")
    source = "estimated" if estimated is True else ("prior" if estimated is False else DASH)
    rows = [
        ("drift position per axis [mm/s]", " / ".join(_fmt(v, 2) for v in pos) or DASH),
        ("drift rotation per axis [mdeg/s]", " / ".join(_fmt(v, 1) for v in rot) or DASH),
        ("drift rates", source),
        ("attitude coupling", f"{_fmt(rates.get('coupling'), 2)}: {rates.get('regime') or DASH}"),
        ("drift correlation time, position / rotation [s]",
         " / ".join(_fmt(v, 0) for v in _numbers(rates.get("correlation_s") or [])) or DASH),
    ]
    components = adj.get("variance_components") or {}
    rows += [(f"variance component {k}", _fmt(v, 3)) for k, v in components.items()]
    rows.append(("variance factor applied", _fmt(adj.get("variance_factor_applied"), 3)))
    by_status = links.get("by_status") or {}
    rows += [
        ("links / candidate pairs", f"{_count(links.get('n_links'))} / "
                                    f"{_count(links.get('n_candidate_pairs'))}"),
        ("links by status", ", ".join(f"{k} {_count(v)}" for k, v in by_status.items()) or DASH),
        ("plane matches (rejected)", f"{_count(links.get('n_matches'))} "
                                     f"({_count(links.get('n_rejected_matches'))})"),
    ]
    model = links.get("model") or {}
    if model.get("estimated"):
        classes = [str(c).replace(">=", "\u2265") for c in model.get("size_classes_m2") or []]
        rows.append((f"links' model, estimated (a-priori \u03c3\u2080 {_fmt(model.get('sigma0_a_priori'), 1)})",
                     "; ".join(f"planes {c} m\u00b2: {_fmt(t, 1)} mrad / {_fmt(o, 1)} mm"
                               for c, t, o in zip(classes, model.get("departure_tilt_mrad") or [],
                                                  model.get("departure_offset_mm") or [], strict=True))
                     + f"; trajectory priors \u00d7{_fmt(model.get('prior_sigma_factor'), 2)}"))
    ranks = links.get("rank_histogram") or {}
    if ranks:
        rows.append(("links by rank", ", ".join(f"{k}: {_count(v)}" for k, v in ranks.items() if v)))
    return _tag("div", "<h3>Drift and network</h3>" + _table(rows), class_="card")


def _timings(report: dict[str, Any]) -> str:
    timings = {str(k): _number(v) for k, v in (_get(report, "timings_s", default={}) or {}).items()}
    if not timings:
        return ""
    longest = max((v for v in timings.values() if v is not None), default=0.0) or 1.0
    body = ""
    for stage, seconds in timings.items():
        bar = f'<span class="bar" style="width:{120 * (seconds or 0) / longest:.0f}px"></span>'
        body += _tag("tr", _tag("td", _esc(stage)) + _tag("td", _esc(_fmt(seconds, 1, "s")), class_="num")
                     + _tag("td", bar))
    total = sum(v for v in timings.values() if v is not None)
    body += _tag("tr", _tag("th", "total") + _tag("th", _esc(_fmt(total, 1, "s")), class_="num")
                 + "<td></td>")
    return _tag("div", "<h3>Timings</h3>" + _tag("table", body), class_="card")


def _rejected_table(report: dict[str, Any]) -> str:
    rejected = _get(report, "adjustment", "rejected_observations", default=[]) or []
    if not rejected:
        return ""
    rows = _rows(report)

    def name(k: Any) -> str:
        return str(rows[k].get("station", k)) if isinstance(k, int) and 0 <= k < len(rows) else str(k)
    table = _table([(str(o.get("kind", DASH)), name(o.get("i")), name(o.get("j"))) for o in rejected
                    if isinstance(o, dict)], header=("kind", "station i", "station j"), numeric_from=9)
    return _tag("details", _tag("summary", f"Rejected observations ({len(rejected)})") + table, open="open")


def _cell(row: dict[str, Any], key: str) -> str:
    value = row.get(key)
    if key in COLUMN_DIGITS:
        return _fmt(value, COLUMN_DIGITS[key])
    if key in ("n_points", "n_planes", "n_links"):
        return _count(value)
    if key == "fixed":
        return "yes" if value else ""
    return DASH if value is None else str(value)


def _station_table(report: dict[str, Any]) -> str:
    rows = _rows(report)
    align = {c: "num" if c in COLUMN_DIGITS or c.startswith("n_") else None for c in STATION_COLUMNS}
    head = _tag("tr", "".join(_tag("th", _esc(c), class_=align[c]) for c in STATION_COLUMNS))
    body = "".join(
        _tag("tr", "".join(_tag("td", _esc(_cell(r, c)), class_=align[c]) for c in STATION_COLUMNS),
             class_="fixed" if r.get("fixed") else None) for r in rows)
    table = _tag("div", _tag("table", head + body, class_="stations"), class_="scroll")
    return _tag("details", _tag("summary", f"Stations ({len(rows)}): the columns of stations.csv, "
                                "orientation \u03c3 [mdeg]") + table)


def _figure(svg: str, caption: str) -> str:
    return _tag("figure", svg + _tag("figcaption", _esc(caption)))


def _plots(report: dict[str, Any]) -> str:
    big = "".join([
        _figure(_plot_plan(report), "Grey: the input trajectory; blue: drift-corrected. Dots: adjusted "
                "stations coloured by their 3D position standard deviation (larger: fixed). Equal scale."),
        _figure(_plot_links(report), "Pairwise links between stations (lines) at the adjusted station "
                "positions; grey dashed: trajectory prior only; red: rejected link; pink: observation "
                "rejected by data snooping in the block adjustment."),
        _figure(_plot_sigma_time(report), "Standard deviations of the adjusted station positions "
                "(static stations without time are not shown)."),
        _figure(_plot_correction(report), "Blue: horizontal distance between the input and the corrected "
                "trajectory. Orange: per station, the gap left after fitting the initial onto the adjusted "
                "station positions with one rigid transformation."),
    ])
    small = "".join(_figure(svg, "Normalised residuals \u221a(T/dof) of the block observations; the curve is "
                            "their expected distribution with a correct a-priori model.")
                    for svg in _plot_histograms(report))
    return _tag("div", big + small, class_="plots")


# --------------------------------------------------------------------------------------------
# The page
# --------------------------------------------------------------------------------------------

def render_html(report: dict[str, Any], base_dir: str | Path | None = None) -> str:
    """One self-contained HTML page (inline CSS and SVG, no network) for a ``report.json`` dict.

    ``report`` is the dictionary of :func:`kinreg.report.json.build_report` or its JSON; missing keys
    and NaN/None values are shown as a dash or an empty plot, never raised. Returns the page text.
    ``base_dir``: the folder the image paths of ``report["cloud"]`` are relative to (the output
    folder); their PNGs are embedded.
    """
    report = _plain(report) if isinstance(report, dict) else {}
    inputs = _get(report, "inputs", default={})
    name = str(inputs.get("cloud") or inputs.get("trajectory") or "")
    runs = [r for r in _get(report, "inputs", "runs", default=[]) if isinstance(r, dict)]
    if not name and len(runs) > 1:
        name = f"{runs[0].get('cloud') or runs[0].get('trajectory') or ''} and {len(runs) - 1} more run(s)"
    version = report.get("kinreg_version", DASH)
    config = report.get("config_toml")
    parts = [
        "<!doctype html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        _tag("title", _esc(f"kinreg report \u2014 {name}" if name else "kinreg report")),
        _tag("style", CSS),
        "</head><body><main>",
        _tag("h1", "kinreg accuracy report"),
        _tag("div", _esc(f"{name} \u00b7 kinreg {version} \u00b7 report schema "
                         f"{report.get('schema_version', DASH)}"), class_="sub"),
        _verdict(report),
        _tag("div", _section_inputs(report) + _key_figures(report) + _drift_and_links(report)
             + _timings(report), class_="cards"),
        _rejected_table(report),
        control_html(report),
        _tag("h2", "Plots"),
        _plots(report),
        cloud_section(report, None if base_dir is None else Path(base_dir)),
        _tag("h2", "Stations and configuration"),
        _station_table(report),
        _tag("details", _tag("summary", "Resolved configuration (config.toml)") + _tag("pre", _esc(config)))
        if config else "",
        _tag("footer", _esc(f"Written by kinreg {version}, HTML report version {REPORT_HTML_VERSION}. "
                            "Units: mm and mdeg; \u03c3: standard deviation.")),
        "</main></body></html>\n",
    ]
    return "\n".join(p for p in parts if p)
