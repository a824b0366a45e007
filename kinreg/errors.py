"""One exception hierarchy for kinreg.

Every failure the user can cause (a bad file, a bad setting, data that cannot be adjusted) raises a
subclass of :class:`KinregError`. The command line turns it into one line and exit code 1; the
library never prints and never exits.
"""

from __future__ import annotations

from os import PathLike
from typing import Any


class KinregError(Exception):
    """Base of every error kinreg raises on purpose.

    ``path`` names the file the problem is in (or ``None``), ``reason`` says what is wrong.
    ``str(error)`` is the one line the command line prints.
    """

    def __init__(self, reason: str, path: str | PathLike[str] | None = None) -> None:
        self.reason = reason
        self.path = None if path is None else str(path)
        super().__init__(f"{self.path}: {reason}" if self.path else reason)


class InputError(KinregError):
    """An input file is missing, unreadable or malformed."""


class TrajectoryError(InputError):
    """A trajectory file is malformed or inconsistent (times, quaternions, values)."""


class CloudError(InputError):
    """A point cloud file is malformed or lacks a required field (e.g. time stamps)."""


class ConfigError(KinregError):
    """A configuration value or a reference-plane file is invalid."""


class OutputError(KinregError):
    """An output cannot be written (exists, folder not writable, disk full)."""


class EstimationError(KinregError):
    """An adjustment cannot be carried out (singular datum, too few observations)."""


class AdjustmentFailedError(EstimationError):
    """The block adjustment ran but gave no result (no convergence, a non-finite value, a
    negative redundancy). ``result`` is the failed adjustment (a :class:`kinreg.types.BlockResult`),
    for a report marked failed; typed loosely here because :mod:`kinreg.types` raises these
    errors, and this module imports nothing of kinreg's."""

    def __init__(self, reason: str, result: Any) -> None:
        super().__init__(reason)
        self.result = result


class CalibrationRejectedError(EstimationError):
    """A calibration was computed but fails its acceptance checks (must not be used as it is)."""
