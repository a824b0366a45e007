"""The ``kinreg`` command: parses arguments, loads the configuration, calls the library, renders
progress and tables. No computation lives here."""

from __future__ import annotations

import logging
import os
import sys
import warnings
from pathlib import Path
from typing import Annotated, Any

import click
import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

import kinreg
from kinreg.config import KinregConfig, WindowMode, format_toml, load_config
from kinreg.errors import KinregError
from kinreg_cli.progress import RichProgress

app = typer.Typer(
    name="kinreg",
    help="Drift correction and block adjustment of kinematic laser scans via quasi-static scans.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console(stderr=True)
out = Console()

CLOUD_SUFFIXES = {".las", ".laz", ".e57"}
WORKERS_HELP = "Local worker processes for per-scan and per-pair work (default: every core; 1: none)."
TrajectoryOption = Annotated[Path, typer.Option("--trajectory", "-t", help="Trajectory file.")]
CloudOption = Annotated[Path, typer.Option("--cloud", "-c", help="Point cloud (LAS/LAZ/E57) with point times.")]
WindowOption = Annotated[float | None, typer.Option("--window-s", help="Window length in seconds.")]
ConfigOption = Annotated[Path | None, typer.Option("--config", help="A kinreg TOML configuration.")]
SCHEDULER_HELP = "Run per-scan and per-pair work on this Dask scheduler, e.g. tcp://host:8786."


def _version(value: bool) -> None:
    if value:
        out.print(f"kinreg {kinreg.__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Print the version and exit.")
    ] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log what each stage does.")] = False,
) -> None:
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="kinreg: %(levelname)s: %(message)s",
        stream=sys.stderr,
    )
    # laspy logs lazrs' IoError at ERROR level just before raising it; kinreg's error line says it.
    logging.getLogger("laspy").setLevel(logging.INFO if verbose else logging.CRITICAL)


def _config(path: Path | None, overrides: dict[str, Any]) -> KinregConfig:
    return load_config(path, overrides)


@app.command()
def info(
    file: Annotated[Path, typer.Argument(
        help="A trajectory (GeoSLAM, TUM, PLY, CSV), a cloud (LAS/LAZ/E57) or reference planes (TOML).")],
    full: Annotated[
        bool, typer.Option("--full", help="Stream the whole cloud for its time range and order.")
    ] = False,
    trajectory_format: Annotated[
        str, typer.Option("--format", help="Trajectory format: auto, geoslam, tum, ply, csv.")
    ] = "auto",
) -> None:
    """What a trajectory or cloud file contains: counts, time range, extent, fields."""
    from kinreg.io.inspect import describe_cloud, describe_trajectory

    if file.suffix.lower() in CLOUD_SUFFIXES:
        rows = describe_cloud(file, full=full, progress=RichProgress(console) if full else None)
    elif file.suffix.lower() == ".toml":
        rows = _describe_reference_planes(file)
    else:
        rows = describe_trajectory(file, None if trajectory_format == "auto" else trajectory_format)
    _print_figures(str(file), rows)


def _print_figures(title: str, rows: list[tuple[str, str]]) -> None:
    """A two-column table of named figures on standard output."""
    table = Table(title=escape(title), show_header=False, title_justify="left")
    table.add_column("", style="bold")
    table.add_column("")
    for key, value in rows:
        table.add_row(escape(key), escape(value))
    out.print(table)


def _describe_reference_planes(path: Path) -> list[tuple[str, str]]:
    from kinreg.io.reference_planes import read_reference_planes

    planes = read_reference_planes(path)
    rows = [("kind", "reference planes"), ("construction accuracy", f"{planes.accuracy_m:g} m"),
            ("planes", f"{len(planes)}"), ("links", f"{len(planes.links)}"),
            ("initial transform", "yes" if planes.T_ref_traj is not None else "no")]
    rows += [(p.name, f"n = [{p.normal[0]:.6f}, {p.normal[1]:.6f}, {p.normal[2]:.6f}], d = {p.d_m:.4f} m")
             for p in planes.planes]
    return rows


@app.command("slice")
def slice_command(
    trajectory: TrajectoryOption,
    cloud: CloudOption,
    out_path: Annotated[Path, typer.Option("--out", "-o", help="The E57 sequence to write.")],
    window_s: WindowOption = None,
    mode: Annotated[WindowMode | None, typer.Option("--mode", help="How windows are cut.")] = None,
    config: ConfigOption = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing output.")] = False,
) -> None:
    """Slice a kinematic run into quasi-static scans and export them as one E57 sequence."""
    from kinreg.run.pipeline import slice_to_e57

    cfg = _config(config, {"slicing.window_s": window_s, "slicing.mode": mode})
    summary = slice_to_e57(trajectory, cloud, out_path, cfg, overwrite=overwrite, progress=RichProgress(console))
    _print_figures("quasi-static sequence", [
        ("scans", f"{summary.n_scans}"),
        ("points in scans", f"{summary.n_points_in_scans:,}"),
        ("points outside trajectory",
         f"{summary.n_points_outside_trajectory:,} ({100 * summary.share_outside:.1f} %)"),
        ("windows skipped", f"{len(summary.skipped)} ({summary.n_points_in_skipped_windows:,} points)"),
        ("written", str(out_path)),
    ])


@app.command("link")
def link_command(
    trajectory: TrajectoryOption,
    cloud: CloudOption,
    out_dir: Annotated[Path, typer.Option("--out", "-o", help="Output folder (planes.csv, links.csv).")],
    config: ConfigOption = None,
    window_s: WindowOption = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace existing results.")] = False,
    workers: Annotated[int | None, typer.Option("--workers", help=WORKERS_HELP)] = None,
    scheduler: Annotated[str | None, typer.Option("--scheduler", help=SCHEDULER_HELP)] = None,
) -> None:
    """Slice, detect planes per scan and adjust every candidate pair (no block adjustment)."""
    from kinreg.run.pipeline import link_to_folder

    cfg = _config(config, {"slicing.window_s": window_s})
    summary = link_to_folder(trajectory, cloud, out_dir, cfg, overwrite=overwrite, progress=RichProgress(console),
                             workers=workers, scheduler=scheduler)
    _print_figures(f"pairwise links in {out_dir}", [
        ("scans", f"{summary.n_scans}"),
        ("planes", f"{summary.n_planes} ({summary.n_planes / max(summary.n_scans, 1):.1f} per scan)"),
        ("candidate pairs", f"{summary.n_candidate_pairs}"),
        ("links", f"{summary.n_links} " + ", ".join(f"{k} {v}" for k, v in summary.by_status.items())),
        ("time", ", ".join(f"{k} {v:.1f} s" for k, v in summary.seconds.items())),
    ])


@app.command("process")
def process_command(
    trajectory: Annotated[list[Path], typer.Option(
        "--trajectory", "-t", help="Trajectory file; repeat it (with --cloud) for several runs in one project.")],
    cloud: Annotated[list[Path], typer.Option(
        "--cloud", "-c", help="Point cloud (LAS/LAZ) with point times; one per --trajectory, paired in order.")],
    out_dir: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")],
    static: Annotated[Path | None, typer.Option("--static", help="Registered static scans (E57 with poses).")] = None,
    reference: Annotated[Path | None, typer.Option("--reference", help="Reference planes (TOML).")] = None,
    control: Annotated[Path | None, typer.Option(
        "--control", help="Control points (CSV name,x,y,z,sigma_mm[,t_start,t_end][,station,sx,sy,sz]): surveyed "
        "points the unit stood on, or targets in a static scan (station: its E57 name; sx,sy,sz: the target in its "
        "frame), observed in the adjustment.")] = None,
    check: Annotated[Path | None, typer.Option(
        "--check", help="Check points (same CSV format): only compared with the corrected trajectory.")] = None,
    config: ConfigOption = None,
    window_s: WindowOption = None,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Start afresh: replace existing results, clear the stage cache.")
    ] = False,
    resume: Annotated[
        bool, typer.Option("--resume", help="Re-use the stage cache of the output folder (an interrupted or earlier "
                           "run): only stages whose inputs changed are done again; the outputs are rewritten.")
    ] = False,
    workers: Annotated[int | None, typer.Option("--workers", help=WORKERS_HELP)] = None,
    scheduler: Annotated[str | None, typer.Option("--scheduler", help=SCHEDULER_HELP)] = None,
) -> None:
    """Run everything: slice, planes, links, block adjustment, corrected outputs, reports."""
    from kinreg.run.pipeline import ProcessInputs, process

    cfg = _config(config, {"slicing.window_s": window_s})
    inputs = ProcessInputs.from_runs(trajectory, cloud, static, reference, control, check)
    summary = process(inputs, out_dir, cfg, overwrite=overwrite, progress=RichProgress(console), workers=workers,
                      scheduler=scheduler, resume=resume)
    verdict = "passed" if summary.global_test_passed else "FAILED (sigmas scaled by sigma0)"
    rows = [("runs", f"{summary.n_runs}")] if summary.n_runs > 1 else []
    rows += [
        ("stations", f"{summary.n_stations}"),
        ("links", f"{summary.n_links}"),
        ("sigma0", f"{summary.sigma0:.3f} (global test {verdict})"),
        ("position sigma", f"RMS {summary.position_sigma_rms_mm:.1f} mm, max {summary.position_sigma_max_mm:.1f} mm"),
        ("gaps before/after", f"mean {summary.gaps_mean_mm:.1f} mm, max {summary.gaps_max_mm:.1f} mm"),
        ("rejected observations", f"{summary.n_rejected}"),
    ]
    if summary.control_rejected is not None:
        rows.append(("control points rejected", ", ".join(summary.control_rejected) or "none"))
    if summary.check_rms_mm is not None:
        rows.append(("check points", f"3D RMS {summary.check_rms_mm:.1f} mm ({summary.check_loa})"))
    rows += [
        ("time", ", ".join(f"{k} {v:.1f} s" for k, v in summary.timings_s.items())),
    ]
    reused = {k: v for k, v in summary.stage_cache.items() if v["reused"]}
    if reused:
        rows.append(("re-used (stage cache)", ", ".join(
            f"{k} {v['reused']}/{v['reused'] + v['computed']}" if v["reused"] + v["computed"] > 1 else k
            for k, v in reused.items())))
    _print_figures(f"kinreg results in {out_dir}", rows)


@app.command("config")
def config_command(
    defaults: Annotated[bool, typer.Option("--defaults", help="Print the default configuration.")] = False,
    config: Annotated[Path | None, typer.Option("--config", help="Resolve and print this file.")] = None,
) -> None:
    """Print the default (or a resolved) configuration as TOML."""
    if not defaults and config is None:
        raise click.UsageError("give --defaults or --config FILE")
    out.print(format_toml(load_config(None if defaults else config)), markup=False, highlight=False)


def _register_optional_commands() -> None:
    """Commands from modules that may not be present in every build."""
    try:
        from kinreg_cli import calibrate as calibrate_module
    except ImportError:
        return
    app.command("calibrate")(calibrate_module.calibrate)
    app.command("plan-calibration")(calibrate_module.plan_calibration)


_register_optional_commands()


# typer >= 0.2x ships its own copy of click (typer._click) and raises its exceptions, not click's;
# older typer raises click's. Both kinds are usage errors and aborts, not internal errors.
_USAGE_ERRORS: tuple[type[Exception], ...] = (click.ClickException,)
_ABORTS: tuple[type[BaseException], ...] = (KeyboardInterrupt, click.exceptions.Abort)
try:
    from typer._click.exceptions import ClickException as _TyperClickException
    from typer.exceptions import Abort as _TyperAbort
except ImportError:  # pragma: no cover  (typer < 0.20 uses click itself)
    pass
else:
    _USAGE_ERRORS += (_TyperClickException,)
    _ABORTS += (_TyperAbort,)

# What typer returns (without standalone mode) when it caught a KeyboardInterrupt.
_INTERRUPTED = 130


def _fail(message: str, code: int) -> None:
    # Plain print, not rich: the one error line must never be wrapped or styled.
    print(f"kinreg: {message}", file=sys.stderr)
    sys.exit(code)


def _one_line_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                      file: object = None, line: str | None = None) -> None:
    # A library warning (numpy's RuntimeWarning, ...) as one line, without the source line.
    text = str(message).strip().splitlines()
    print(f"kinreg: warning: {category.__name__}: {text[0] if text else ''}", file=sys.stderr)


_TRACKER_QUIET = "ignore::UserWarning:multiprocessing.resource_tracker"


def main(argv: list[str] | None = None) -> None:
    """Entry point: one clean line and exit code 1 for every kinreg error, no traceback."""
    warnings.showwarning = _one_line_warning
    # Python's resource tracker (a process of its own, started with this interpreter's -W flags)
    # warns of "leaked" semaphores when Ctrl-C ends the workers while their queues are being
    # unlinked, and then that it could not unlink them: nothing leaked, but the lines followed
    # "kinreg: interrupted" (CI, under load).
    if _TRACKER_QUIET not in sys.warnoptions:
        sys.warnoptions.append(_TRACKER_QUIET)
    try:
        code = app(args=argv, standalone_mode=False)
    except KinregError as e:
        _fail(f"error: {e}", 1)
    except _ABORTS:
        _fail("interrupted", _INTERRUPTED)
    except _USAGE_ERRORS as e:
        e.show()  # type: ignore[attr-defined]
        sys.exit(e.exit_code)  # type: ignore[attr-defined]
    except OSError as e:
        where = f"{e.filename}: " if getattr(e, "filename", None) else ""
        _fail(f"error: {where}{e.strerror or e}", 1)
    except Exception as e:  # an internal error: say so in one line unless debugging
        if os.environ.get("KINREG_DEBUG"):
            raise
        _fail(f"internal error: {type(e).__name__}: {e} (set KINREG_DEBUG=1 for the traceback)", 2)
    if code == _INTERRUPTED:
        _fail("interrupted", _INTERRUPTED)
    sys.exit(code if isinstance(code, int) else 0)
