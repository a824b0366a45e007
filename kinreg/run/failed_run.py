"""A run whose block adjustment gave no result: its outputs (of an earlier run too) removed, and
with ``[block] on_failure = "report"`` a ``report.json`` and ``report.html`` marked failed."""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

from kinreg.config import KinregConfig, OnFailure, format_toml
from kinreg.errors import AdjustmentFailedError
from kinreg.estimate.network import Network
from kinreg.estimate.strategy import adjustment_failure
from kinreg.report.cloud_views import FIGURES_DIR
from kinreg.report.html import render_html
from kinreg.report.json import build_failure_report, write_report_json
from kinreg.report.tables import format_links_csv, format_planes_csv, links_table, write_text
from kinreg.run.output_folder import RunCache
from kinreg.types import BlockResult, Plane


def fail_adjustment(result: BlockResult, network: Network, config: KinregConfig, folder: RunCache,
                    report_inputs: dict[str, Any], planes: Sequence[tuple[Plane, ...]] | None = None) -> NoReturn:
    """Raise :class:`AdjustmentFailedError` for the failed ``result`` of ``network``, the folder's
    outputs (of an earlier run too) removed, and with ``[block] on_failure = "report"`` a
    ``report.json`` and ``report.html`` marked failed in their place, with ``links.csv`` and (with
    the stations' ``planes``) ``planes.csv``: what a user needs to see why."""
    if config.block.on_failure is OnFailure.REPORT:
        staging = folder.start_outputs()
        report = build_failure_report(inputs=report_inputs, config_toml=format_toml(config), result=result,
                                      datum=network.datum.description, alpha=config.block.alpha, network=network,
                                      planes=planes)
        write_text(staging / "links.csv", format_links_csv(links_table(network.links, None)))
        if planes is not None:
            write_text(staging / "planes.csv", format_planes_csv(network.stations, planes))
        write_text(staging / "report.html", render_html(report))
        write_report_json(staging / "report.json", report)
    folder.commit_outputs()
    shutil.rmtree(folder.out_dir / FIGURES_DIR, ignore_errors=True)  # the report's images of an earlier run
    if config.block.on_failure is not OnFailure.REPORT:
        raise AdjustmentFailedError(checked_reason(result), result) from None
    raise AdjustmentFailedError(checked_reason(result, report_in=folder.out_dir), result) from None


def checked_reason(result: BlockResult, report_in: Path | None = None) -> str:
    """The line a failed adjustment ends the run with; ``report_in``: the folder where a report
    marked failed was written (``[block] on_failure = "report"``)."""
    head = adjustment_failure(result)
    if report_in is not None:
        return (f"{head}; report.json and report.html in {report_in} are marked failed, with links.csv and "
                "planes.csv to see why; nothing else was written")
    return (f"{head}; nothing was written. Check the links in a `kinreg link` run, or set [block] on_failure = "
            '"report" to keep a report marked failed')
