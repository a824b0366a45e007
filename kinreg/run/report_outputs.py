"""The reports of ``kinreg process``: ``report.json`` built in one call from the run's results,
and the tables and pages written from it (``stations.csv``, ``links.csv``, ``config.toml``,
``report.html``, ``control_points.csv``)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from kinreg.config import KinregConfig, format_toml
from kinreg.estimate.control import Assignment
from kinreg.estimate.correction import DriftCorrection
from kinreg.estimate.drift import DriftRates
from kinreg.estimate.network import Network, station_pairs
from kinreg.report.control import check_section, control_section, format_control_points_csv
from kinreg.report.html import render_html
from kinreg.report.json import build_report, write_report_json
from kinreg.report.tables import (
    format_links_csv,
    format_planes_csv,
    format_stations_csv,
    links_table,
    stations_table,
    write_text,
)
from kinreg.run.context import RunContext
from kinreg.run.estimation import Estimated
from kinreg.run.large_outputs import WrittenOutputs
from kinreg.run.runs import inputs_report, slicing_report, trajectory_plot
from kinreg.types import BlockResult, Plane, Trajectory


@dataclass(frozen=True, eq=False)
class ProcessResults:
    """Everything the report of a processed run is made of."""

    estimated: Estimated
    corrections: list[DriftCorrection]
    written: WrittenOutputs


def write_reports(run: RunContext, results: ProcessResults) -> dict[str, Any]:
    """``report.json`` (:func:`process_report`) and the tables and pages made from it, into the
    staging folder; ``report.json`` last. Returns the report."""
    adjusted, staging = results.estimated.adjusted, run.folder.staging
    report = process_report(run, results)
    write_tables(staging, report, adjusted.network, adjusted.result, results.estimated.planes,
                 figures_dir=run.folder.out_dir)
    run.clock.lap("reports")
    write_report_json(staging / "report.json", report)
    return report


def process_report(run: RunContext, results: ProcessResults) -> dict[str, Any]:
    """The content of ``report.json`` (:func:`~kinreg.report.json.build_report`, and the control
    and check points' sections where they were given); the cloud views' figures go straight into
    the output folder's ``figures``."""
    estimated, inputs, read = results.estimated, run.inputs, run.read
    config, adjusted, kinematic, sliced = estimated.config, estimated.adjusted, estimated.kinematic, estimated.sliced
    static = config.static if inputs.static is not None else None
    given = {k: str(p) for k, p in (("control", inputs.control), ("check", inputs.check)) if p}
    est = estimated.estimate
    report = build_report(
        inputs={**inputs_report(inputs.runs, kinematic.trajectories, sliced, inputs.static, inputs.reference),
                **given},
        config_toml=format_toml(config), network=adjusted.network, planes=estimated.planes,
        n_candidate_pairs=len(station_pairs(estimated.stations, config.matching, static)), result=adjusted.result,
        drift_rates=adjusted.rates, slicing=slicing_report([slices.summary for slices in sliced], config.slicing,
                                                           est.smear_m, est.first_window_s, est.points_deskewed),
        corrections=results.corrections, jumps=kinematic.jumps, references=read.references,
        stage_cache=run.folder.summary(), alpha=config.block.alpha, timings_s=run.clock.timings_s,
        trajectory_plot=trajectory_plot(kinematic.trajectories, results.written.corrected),
        misfits=adjusted.misfits,
        cloud_views=results.written.views.finish(run.folder.out_dir))  # "cloud" and "crs"
    return {**report, **points_report(adjusted.network, adjusted.result, adjusted.rates, read.control, read.check,
                                      kinematic.trajectories, results.corrections, config)}


def write_tables(out: Path, report: dict[str, Any], network: Network, result: BlockResult,
                 planes: Sequence[tuple[Plane, ...]], figures_dir: Path | None = None) -> None:
    """``stations.csv``, ``links.csv``, ``planes.csv``, ``config.toml`` and ``report.html``
    (``report.json`` is written last); the report's images are read from ``figures_dir`` (default
    ``out``)."""
    rows = stations_table(network.stations, result, planes, network.links)
    write_text(out / "stations.csv", format_stations_csv(rows))
    write_text(out / "links.csv", format_links_csv(links_table(network.links, result, network.plane_nodes)))
    write_text(out / "planes.csv", format_planes_csv(network.stations, planes))
    write_text(out / "config.toml", report["config_toml"])
    write_text(out / "report.html", render_html(report, base_dir=figures_dir or out))
    # always written (only its header without --control/--check): every name in OUTPUT_FILES is
    # in every finished run's folder, so that no file of an earlier run is left there
    write_text(out / "control_points.csv", format_control_points_csv(report))


def points_report(network: Network, result: BlockResult, rates: DriftRates, control: Assignment | None,
                  check: Assignment | None,
                  trajectories: Sequence[Trajectory], corrections: Sequence[DriftCorrection],
                  config: KinregConfig) -> dict[str, Any]:
    """``report.json``'s ``control`` and ``check`` sections (only those given)."""
    reference = np.asarray(config.control.reference_point_m)
    out: dict[str, Any] = {}
    if control is not None:
        out["control"] = control_section(network, result, rates, control, trajectories, corrections, reference,
                                         config.block.alpha)
    if check is not None:
        out["check"] = check_section(check, trajectories, corrections, reference, network.stations, result)
    return out
