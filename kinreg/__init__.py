"""kinreg: drift correction and geodetic block adjustment of kinematic laser scans.

The API a script uses::

    import kinreg

    config = kinreg.load_config("my.toml")                     # or load_config() for the defaults
    inputs = kinreg.ProcessInputs.from_runs(["run/traj.txt"], ["run/cloud.laz"])
    summary = kinreg.process(inputs, "out/run", config)        # raises kinreg.KinregError on bad input
    print(summary.position_sigma_rms_mm, summary.global_test_passed)

The names below are loaded on first use (the pipeline pulls in scipy; a script that only reads a
trajectory should not pay for it). Layers and modules: ``ARCHITECTURE.md``.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from kinreg import _logging  # noqa: F401  (attaches the NullHandler)
from kinreg._version import __version__

# public name -> module that defines it
_API = {
    "process": "kinreg.run.pipeline",
    "link_to_folder": "kinreg.run.pipeline",
    "slice_to_e57": "kinreg.run.pipeline",
    "ProcessInputs": "kinreg.run.pipeline",
    "ProcessSummary": "kinreg.run.pipeline",
    "LinkSummary": "kinreg.run.pipeline",
    "load_config": "kinreg.config",
    "KinregConfig": "kinreg.config",
    "read_trajectory": "kinreg.io.trajectory",
    "open_cloud": "kinreg.io.cloud",
    "read_reference_planes": "kinreg.io.reference_planes",
    "KinregError": "kinreg.errors",
    "InputError": "kinreg.errors",
    "TrajectoryError": "kinreg.errors",
    "CloudError": "kinreg.errors",
    "ConfigError": "kinreg.errors",
    "OutputError": "kinreg.errors",
    "EstimationError": "kinreg.errors",
    "Pose": "kinreg.geometry",
    "Trajectory": "kinreg.types",
    "Scan": "kinreg.types",
    "Plane": "kinreg.types",
    "Station": "kinreg.types",
    "Link": "kinreg.types",
    "BlockResult": "kinreg.types",
}
__all__ = [
    "BlockResult",
    "CloudError",
    "ConfigError",
    "EstimationError",
    "InputError",
    "KinregConfig",
    "KinregError",
    "Link",
    "LinkSummary",
    "OutputError",
    "Plane",
    "Pose",
    "ProcessInputs",
    "ProcessSummary",
    "Scan",
    "Station",
    "Trajectory",
    "TrajectoryError",
    "__version__",
    "link_to_folder",
    "load_config",
    "open_cloud",
    "process",
    "read_reference_planes",
    "read_trajectory",
    "slice_to_e57",
]

if TYPE_CHECKING:
    from kinreg.config import KinregConfig, load_config
    from kinreg.errors import (
        CloudError,
        ConfigError,
        EstimationError,
        InputError,
        KinregError,
        OutputError,
        TrajectoryError,
    )
    from kinreg.geometry import Pose
    from kinreg.io.cloud import open_cloud
    from kinreg.io.reference_planes import read_reference_planes
    from kinreg.io.trajectory import read_trajectory
    from kinreg.run.pipeline import (
        LinkSummary,
        ProcessInputs,
        ProcessSummary,
        link_to_folder,
        process,
        slice_to_e57,
    )
    from kinreg.types import BlockResult, Link, Plane, Scan, Station, Trajectory


def __getattr__(name: str) -> Any:
    if name in _API:
        value = getattr(importlib.import_module(_API[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'kinreg' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
