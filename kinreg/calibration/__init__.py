"""System calibration of a kinematic laser scanner (lever arm + boresight) from reference planes,
and planning of the calibration field (seed 000; METHOD.md section 3).

Public API:

- :func:`calibrate_robust` (points found amid the room, coarse to fine, then the adjustment),
  :func:`calibration_problems` (why a result must not be used), :class:`AssignmentConfig`.
- :func:`estimate_calibration` (Gauss-Helmert adjustment), :func:`assign_points_to_planes`,
  :class:`SystemCalibration`, :class:`CalibrationConfig`, :class:`CalibrationResult`.
- :func:`evaluate_arrangement`, :func:`exhaustive_search`, :func:`optimise_evolution`,
  :class:`PlanningConfig`, :class:`Table3Grid`, :func:`table2_arrangement`, :func:`read_arrangement`.
- :func:`simulate_calibration` (ground truth for tests).
- :func:`calibration_report`, :func:`calibration_text`, :func:`planning_report`,
  :func:`planning_text`, :func:`write_report`.
"""

from kinreg.calibration.arrangement import PlanePatch, read_arrangement, table2_arrangement
from kinreg.calibration.assignment import (
    AssignmentConfig,
    RobustCalibration,
    calibrate_robust,
    calibration_problems,
)
from kinreg.calibration.model import (
    PARAMETER_NAMES,
    CalibrationConfig,
    CalibrationResult,
    ScannerSigmas,
    SystemCalibration,
    TrackerSigmas,
    assign_points_to_planes,
    calibrate_with_gating,
    estimate_calibration,
)
from kinreg.calibration.planning import (
    ArrangementQuality,
    GridResult,
    PlanningConfig,
    Table3Grid,
    evaluate_arrangement,
    exhaustive_search,
    optimise_evolution,
)
from kinreg.calibration.report import (
    calibration_report,
    calibration_text,
    planning_report,
    planning_text,
    write_report,
)
from kinreg.calibration.simulate import (
    RoomConfig,
    SimulatedCalibration,
    SimulationConfig,
    room_scenario,
    simulate_calibration,
)

__all__ = [
    "PARAMETER_NAMES",
    "ArrangementQuality",
    "AssignmentConfig",
    "CalibrationConfig",
    "CalibrationResult",
    "GridResult",
    "PlanePatch",
    "PlanningConfig",
    "RobustCalibration",
    "RoomConfig",
    "ScannerSigmas",
    "SimulatedCalibration",
    "SimulationConfig",
    "SystemCalibration",
    "Table3Grid",
    "TrackerSigmas",
    "assign_points_to_planes",
    "calibrate_robust",
    "calibrate_with_gating",
    "calibration_problems",
    "calibration_report",
    "calibration_text",
    "estimate_calibration",
    "evaluate_arrangement",
    "exhaustive_search",
    "optimise_evolution",
    "planning_report",
    "planning_text",
    "read_arrangement",
    "room_scenario",
    "simulate_calibration",
    "table2_arrangement",
    "write_report",
]
