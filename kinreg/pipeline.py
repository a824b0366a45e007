"""The pipelines, readable top to bottom: each line names one stage."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from kinreg.config import InputConfig, KinregConfig
from kinreg.io.atomic import check_writable_target
from kinreg.io.cloud import open_cloud
from kinreg.io.trajectory import parse_column_mapping, read_trajectory
from kinreg.progress import NullProgress, Progress
from kinreg.slicing import QuasiStaticSequence, SlicingSummary, slice_quasi_static
from kinreg.types import Scan, Trajectory


def read_input_trajectory(path: str | Path, config: InputConfig) -> Trajectory:
    """The trajectory named in the inputs, read with the configured format and column mapping."""
    fmt = None if config.trajectory_format == "auto" else config.trajectory_format
    columns = parse_column_mapping(config.trajectory_columns) if config.trajectory_columns else None
    return read_trajectory(path, fmt, columns)


def _counted(scans: Iterator[Scan], progress: Progress, stage: str, total: int) -> Iterator[Scan]:
    progress.start(stage, total=total, unit="scans")
    for scan in scans:
        yield scan
        progress.advance(1)
    progress.finish()


def slice_to_e57(
    trajectory_path: str | Path,
    cloud_path: str | Path,
    out_path: str | Path,
    config: KinregConfig,
    overwrite: bool = False,
    progress: Progress | None = None,
) -> SlicingSummary:
    """``kinreg slice``: read, slice into quasi-static scans, export one E57 sequence."""
    from kinreg.io.e57 import write_e57_sequence

    progress = progress or NullProgress()
    check_writable_target(Path(out_path), overwrite)  # fail before the long work, not after
    trajectory = read_input_trajectory(trajectory_path, config.input)
    with open_cloud(cloud_path) as cloud:
        sequence: QuasiStaticSequence = slice_quasi_static(
            trajectory, cloud, config.slicing, config.input.chunk_points, progress=progress
        )
    with sequence:
        scans = _counted(sequence.iter_scans(), progress, "export E57", len(sequence))
        write_e57_sequence(out_path, scans, overwrite=overwrite)
    return sequence.summary
