"""What ``kinreg process`` reads, read and checked against each other before the long work."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from kinreg.config import InputConfig, KinregConfig
from kinreg.errors import ConfigError
from kinreg.estimate.control import Assignment, assign_points
from kinreg.estimate.reference import to_reference_frame
from kinreg.io.checks import check_inputs
from kinreg.io.control import read_control_points
from kinreg.io.reference_planes import ReferencePlanes, read_reference_planes
from kinreg.io.trajectory import parse_column_mapping, read_trajectory
from kinreg.run.planes_stage import static_scan_names
from kinreg.run.runs import RunInputs
from kinreg.types import Trajectory


@dataclass(frozen=True)
class ProcessInputs:
    """What ``kinreg process`` reads: one or several runs (``trajectory`` and ``cloud`` are the
    first, ``more_runs`` the others, in order; see :mod:`kinreg.run.runs`), static scans, reference planes."""

    trajectory: Path
    cloud: Path
    static: Path | None = None
    reference: Path | None = None
    more_runs: tuple[RunInputs, ...] = ()
    control: Path | None = None  # control points (CSV): observations of the adjustment
    check: Path | None = None  # check points (CSV): only compared

    @property
    def runs(self) -> tuple[RunInputs, ...]:
        return (RunInputs(Path(self.trajectory), Path(self.cloud)), *self.more_runs)

    @classmethod
    def from_runs(cls, trajectories: Sequence[str | Path], clouds: Sequence[str | Path],
                  static: Path | None = None, reference: Path | None = None, control: Path | None = None,
                  check: Path | None = None) -> ProcessInputs:
        """Runs paired in order: ``trajectories[k]`` with ``clouds[k]``. Raises :class:`ConfigError`
        when the counts differ, none is given, or a file is given twice."""
        if len(trajectories) != len(clouds):
            raise ConfigError(f"{len(trajectories)} trajectories (--trajectory) but {len(clouds)} clouds (--cloud): "
                              "give one cloud per trajectory, paired in order")
        if not trajectories:
            raise ConfigError("no run given: give a trajectory (--trajectory) and its cloud (--cloud)")
        runs = [RunInputs(Path(t), Path(c)) for t, c in zip(trajectories, clouds, strict=True)]
        for paths in ([r.trajectory for r in runs], [r.cloud for r in runs]):
            seen = [path.resolve() for path in paths]
            twice = next((path for k, path in enumerate(paths) if seen[k] in seen[:k]), None)
            if twice is not None:
                raise ConfigError("given for two runs", twice)
        return cls(runs[0].trajectory, runs[0].cloud, static, reference, tuple(runs[1:]), control, check)


@dataclass(frozen=True, eq=False)
class ReadInputs:
    """The inputs of ``kinreg process`` as read: each run's trajectory, the reference planes, the
    control and check points (``None`` where not given)."""

    trajectories: list[Trajectory]
    references: ReferencePlanes | None
    control: Assignment | None
    check: Assignment | None


def read_inputs(inputs: ProcessInputs, config: KinregConfig) -> ReadInputs:
    """Read the reference planes, the runs' trajectories and the control and check points, each
    checked against the others (the clouds are only opened by the slicing). Raises
    :class:`~kinreg.errors.InputError` or :class:`~kinreg.errors.ConfigError` for a bad input."""
    references = read_reference_planes(inputs.reference) if inputs.reference is not None else None
    trajectories = read_run_trajectories(inputs.runs, config.input, inputs.static)
    control, check = read_points(inputs, trajectories, references, config)
    return ReadInputs(trajectories, references, control, check)


def read_input_trajectory(path: str | Path, config: InputConfig) -> Trajectory:
    """The trajectory named in the inputs, read with the configured format and column mapping."""
    fmt = None if config.trajectory_format == "auto" else config.trajectory_format
    columns = parse_column_mapping(config.trajectory_columns) if config.trajectory_columns else None
    return read_trajectory(path, fmt, columns)


def read_run_trajectories(runs: Sequence[RunInputs], config: InputConfig,
                          static: Path | None = None) -> list[Trajectory]:
    """Each run's trajectory, after the inputs are checked against each other before the long work
    (:func:`~kinreg.io.checks.check_inputs`: time bases, static scans); a run whose cloud cannot
    be written corrected is refused first."""
    for r in runs:
        if r.cloud.suffix.lower() not in (".las", ".laz"):
            raise ConfigError("writing the corrected cloud from an E57 input is not supported yet", r.cloud)
    trajectories = [read_input_trajectory(r.trajectory, config) for r in runs]
    check_inputs([r.cloud for r in runs], trajectories, static, config)
    return trajectories


def read_points(inputs: ProcessInputs, trajectories: Sequence[Trajectory], references: ReferencePlanes | None,
                config: KinregConfig) -> tuple[Assignment | None, Assignment | None]:
    """The control and check points (``--control``, ``--check``), each with its stand-still on the
    trajectories (moved into the reference frame, as the stations will be), or its static scan
    (``--static``); ``None`` where not given. Raises :class:`~kinreg.errors.InputError` for a bad
    file or one whose points tie to nothing."""
    moved = [to_reference_frame([], t, references)[1] for t in trajectories]
    found = []
    scans = static_scan_names(inputs.static) if inputs.static is not None else None
    for path, what in ((inputs.control, "control"), (inputs.check, "check")):
        found.append(None if path is None else assign_points(read_control_points(path), moved, config.control, what,
                                                             scans))
    if found[0] is not None and found[1] is not None and set(found[0].all_names) & set(found[1].all_names):
        both = ", ".join(sorted(set(found[0].all_names) & set(found[1].all_names))[:5])
        raise ConfigError(f"point(s) {both} are both control and check points: a check point must stay out of the "
                          "adjustment", inputs.check)
    return found[0], found[1]
