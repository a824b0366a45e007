"""Configuration: one typed model, a section per stage, loaded from TOML.

Each stage receives only its own section. ``kinreg config --defaults`` prints
:func:`format_toml` of :class:`KinregConfig` with its defaults; every run writes the resolved
configuration next to its results.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import math
import sys
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from kinreg.errors import ConfigError

log = logging.getLogger(__name__)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

# Bump when a key is renamed or removed (adding keys with defaults does not need a bump).
# 2: [matching] max_jump_m and [block] drift_per_axis removed (_REMOVED).
# 3: [control] max_speed_mps, max_rotation_deg_per_s, smoothing_s removed (_REMOVED).
CONFIG_SCHEMA_VERSION = 3

# Keys that earlier versions knew, with the value that left their feature off. A file that still
# sets one to that value (a config.toml an earlier run wrote) asks for nothing that is gone: it
# loads, with a warning. Any other value asked for a behaviour kinreg no longer has: refused, as
# an unknown key is, but saying why.
_REMOVED: dict[tuple[str, str], tuple[Any, str]] = {
    ("matching", "max_jump_m"): (0.0, "the translation search of pairs across a trajectory jump was "
                                      "an experiment that stayed off; jumps are found in the trajectory ([jumps])"),
    ("block", "drift_per_axis"): (False, "the variance components of the drift per object axis were "
                                         "an experiment that stayed off"),
    # Their defaults, as an earlier run's config.toml holds them: a stand-still is now found from
    # where the unit stays, not from its speed (max_radius_m, max_rotation_deg, window_s).
    ("control", "max_speed_mps"): (0.02, "stand-stills are found from the ball the unit stays in: max_radius_m"),
    ("control", "max_rotation_deg_per_s"): (2.0, "stand-stills are found from the unit's turn over the "
                                                 "window: max_rotation_deg"),
    ("control", "smoothing_s"): (0.5, "stand-stills are judged over window_s"),
}


class WindowMode(enum.Enum):
    """How the trajectory is cut into quasi-static scans."""

    DURATION = "duration"  # windows of about `window_s` seconds
    PATH = "path"  # windows of about `window_path_m` metres of path
    POINTS = "points"  # windows of about `window_points` points


@dataclasses.dataclass(frozen=True)
class InputConfig:
    trajectory_format: str = "auto"  # auto, geoslam, tum, ply or csv
    trajectory_columns: str = ""  # CSV only, e.g. "time=gps_time,x=E,y=N,z=H,qw=q0,qx=q1,qy=q2,qz=q3"
    chunk_points: int = 2_000_000  # points decoded per block; bounds memory, not results
    # Added to every point time of the cloud to put it in the trajectory's time base, e.g. -18 for a
    # cloud in GPS time and a trajectory in UTC (kinreg names the likely offset when they differ).
    cloud_time_offset_s: float = dataclasses.field(default=0.0, metadata={"signed": True})
    # Largest share of a cloud's points that may be left out for a non-finite time or a time outside
    # the trajectory's range; more stops the run before the long work.
    max_dropped_share: float = dataclasses.field(default=0.05, metadata={"share": True})
    check_time_base: bool = True  # false: skip the comparison of the cloud's and trajectory's time bases


@dataclasses.dataclass(frozen=True)
class SlicingConfig:
    mode: WindowMode = WindowMode.DURATION
    window_s: float = 6.0  # the seed used 5-7 s windows (26.5 min -> 231 scans)
    window_path_m: float = 6.0
    window_points: int = 1_000_000
    min_points: int = 2000  # windows with fewer points are reported and skipped
    temp_dir: str = ""  # where per-window points are spilled; "" means the system default
    # A LAZ cloud's decoded points are also kept in the spill (its record size per point, 30-38
    # bytes where the spill takes 24), where the disk has room: the corrected cloud is then
    # written without decoding the LAZ a second time. No result depends on it.
    keep_decoded: bool = True
    # Windows that stay quasi-static (duration mode): after the first adjustment, where the drift
    # measured over half a window (the smear) exceeds this share of the planes' noise, the run is
    # sliced again with windows short enough, not below min_window_s (plane detection needs a
    # full sweep of the head). Between max_smear_share and shown_smear_share of the noise, only
    # where the first network's scan-plane offsets show the smear (their residuals reject their
    # model: an offset kind's chi-square test at [block] alpha); beyond it in any case.
    adaptive: bool = True
    max_smear_share: float = 0.5
    shown_smear_share: float = 1.0
    min_window_s: float = 2.0
    # Where the attitude error turns the trajectory's steps (GNSS/INS-like: a measured coupling
    # above 0.75) and shears the windows by more than the range noise, the planes were chosen from
    # sheared points: the windows' points are deskewed with the first adjustment and their planes
    # detected, linked and adjusted again (the planes' stage and what follows it, twice).
    deskew_sheared: bool = True


@dataclasses.dataclass(frozen=True)
class PlanesConfig:
    voxel_m: float = 0.1  # RANSAC runs on a voxel-downsampled copy; the refit uses all points
    distance_m: float = 0.03  # RANSAC inlier threshold; about 3 x the range noise
    refit_distance_m: float = 0.03  # full-resolution inlier band around the plane; about 3 x the noise
    max_planes: int = 30  # patches per scan (the largest are kept); RANSAC stops at this many planes
    ransac_iterations: int = 256  # plane hypotheses (local planar cells) scored per RANSAC round
    ransac_cell_m: float = 0.5  # cell size of the local plane hypotheses
    ransac_sample_points: int = 2048  # downsampled points the hypotheses are first scored on
    min_points: int = 500  # full-resolution inliers per patch
    min_area_m2: float = 1.0  # patches whose convex hull is smaller than this are dropped
    patch_cell_m: float = 0.25  # grid cell for splitting disconnected patches of one plane
    patch_min_cell_points: int = 2  # grid cells with fewer inliers do not connect (stray points)
    # Floors added in quadrature to the least-squares sigmas: quasi-static scans have correlated
    # errors (drift inside the window, incidence-angle range bias, wall unevenness) that the
    # point-count-driven LS covariance (~0.03 mm for 1e5 points) does not see. The drift inside
    # the window is added per plane on top (kinreg.estimate.network.with_window_deformation). Chosen with
    # the normalised station errors of repeated simulated runs (benchmarks/RESULTS.md): 0.5 mm /
    # 0.2 mrad gave 0.6-0.7 (too conservative), 0.25 mm / 0.1 mrad worse stations.
    min_sigma_d_m: float = 0.00035
    min_sigma_angle_rad: float = 0.00014
    seed: int = 0  # RANSAC seed: the same seed gives the same planes


@dataclasses.dataclass(frozen=True)
class DriftConfig:
    """How fast the trajectory's relative error grows with the time between two poses.

    sigma(dt) = sqrt(floor^2 + (rate * dt)^2), per axis. It weights the trajectory's own links
    between stations and the prior of every pairwise adjustment, and it sets the bias of a
    quasi-static scan (drift inside its window, see ``kinreg.estimate.drift.window_bias_covariance``).
    Defaults describe a handheld SLAM unit of the GeoSLAM class (a few mm over a 6 s window,
    1-3 cm over 100 m); set them from your scanner's specification.

    The rates are a prior: the block adjustment measures the drift (the error of the
    trajectory's relative motion between stations) and adjusts again with the measured rates, faster or slower
    than the prior, but never below ``measured_rate_floor`` times the prior (a direction no plane
    fixes shows no drift in the corrections, which would otherwise read as none at all).
    """

    sigma_pos_floor_m: float = 0.001
    sigma_pos_m_per_s: float = 0.0003
    sigma_rot_floor_deg: float = 0.01
    sigma_rot_deg_per_s: float = 0.003
    measured_rate_floor: float = 0.25
    # Measure how long the drift velocity stays alike (its correlation time) and carry it as an
    # unknown per trajectory link (kinreg.estimate.drift.drift_observation); false: the links'
    # drift is taken as independent from one link to the next.
    measure_correlation: bool = True


@dataclasses.dataclass(frozen=True)
class MatchingConfig:
    neighbour_depth: int = 4  # each scan is linked to this many successors in the sequence
    radius_m: float = 10.0  # and to any scan whose centre is this close (loop closures)
    # At most this many loop-closure candidates a scan, spread over the passes through its radius
    # (a long run passes every place dozens of times; 0: every scan within radius_m).
    max_loop_pairs: int = dataclasses.field(default=40, metadata={"allow_zero": True})
    max_angle_deg: float = 2.0  # normal angle between candidate planes after the approximate transform
    max_offset_m: float = 0.10  # offset between candidate planes after the approximate transform
    min_overlap: float = 0.1  # overlapping share of the smaller extent
    coplanar_angle_deg: float = 1.0  # patches closer than this are one physical plane ...
    coplanar_offset_m: float = 0.02  # ... if also this close
    min_matches: int = 3  # a pair with fewer plane matches is not linked


@dataclasses.dataclass(frozen=True)
class PairwiseConfig:
    alpha: float = 0.001  # significance of the global test and of data snooping
    max_iterations: int = 10
    max_rejected_share: float = 0.3  # stop snooping (and fail the link) beyond this share of matches
    # Prior of a pair of quasi-static stations from two different runs: no trajectory ties them,
    # only the runs' common frame (a few cm, tenths of a degree), so it is as loose as for a static scan.
    cross_run_prior_sigma_m: float = 0.2
    cross_run_prior_sigma_deg: float = 1.0


class Disconnected(enum.Enum):
    """What to do with parts of the network that no link ties to the datum."""

    STOP = "stop"  # stop with a message naming the parts
    FIX_EACH = "fix_each"  # adjust each part in its own datum: its first station held fixed


class OnFailure(enum.Enum):
    """What to do when the block adjustment fails (no convergence, NaN, negative redundancy)."""

    STOP = "stop"  # one line, exit 1, no outputs
    REPORT = "report"  # also write report.json / report.html marked failed (no other outputs)


@dataclasses.dataclass(frozen=True)
class BlockConfig:
    alpha: float = 0.001  # significance of the global test and of data snooping
    # Levenberg-Marquardt iterations per adjustment round (a 0.5 m drift from a cold start: 20-30; a
    # scan frame its planes fix to a metre along one axis, pulled by a wrong link: about 70)
    max_iterations: int = 200
    convergence: float = 1e-9  # converged when no unknown changes by more (m or rad) ...
    cost_tolerance: float = 1e-12  # ... or the weighted squared residuals fall by less than this share
    data_snooping: bool = True
    max_rejections: int = 50
    # Estimate one variance factor per observation kind, used only to inflate the a-priori model
    # (errors shared by all links of a scan and smooth drift do not show in residuals).
    variance_components: bool = True
    max_variance_rounds: int = 10
    disconnected: Disconnected = Disconnected.STOP
    on_failure: OnFailure = OnFailure.STOP
    # Match the pairs again from the adjusted poses and adjust again, until the linked pairs no
    # longer change (loop closures across the accumulated drift), at most this often (and up to two
    # rounds more while the measured coupling of the drift settles: kinreg.estimate.strategy._settled_coupling).
    max_relink_rounds: int = 2
    # A scan frame and a sensor pose per quasi-static station, tied by the window bias (one error
    # shared by all the scan's plane links: kinreg.estimate.frames); false: one pose per station,
    # the window bias added to the trajectory's links and to the reported covariances.
    scan_frames: bool = True
    # The last adjustment observes each scan's planes once, the physical planes (clusters of the
    # links' matches) as unknowns, instead of the links (kinreg.estimate.plane_nodes; with scan_frames).
    plane_nodes: bool = True


class StaticDatum(enum.Enum):
    """How registered static scans enter the network."""

    FIXED = "fixed"  # their poses are the datum, held fixed
    OBSERVED = "observed"  # their poses are observations with static_sigma_mm / static_sigma_mdeg


@dataclasses.dataclass(frozen=True)
class StaticConfig:
    datum: StaticDatum = StaticDatum.FIXED
    sigma_mm: float = 2.0  # standard deviation of each static position (datum = "observed")
    sigma_mdeg: float = 5.0  # ... and of each static orientation angle
    link_radius_m: float = 15.0  # quasi-static scans this close to a static scan are linked to it
    prior_sigma_m: float = 0.2  # prior of a static-to-quasi-static pairwise adjustment (no trajectory ties them)
    prior_sigma_deg: float = 1.0


@dataclasses.dataclass(frozen=True)
class ReferenceConfig:
    angle_gate_deg: float = 5.0  # a detected plane is tied to a reference plane within this angle ...
    distance_gate_m: float = 0.3  # ... and this distance (the trajectory frame is roughly the building's)
    ambiguity_ratio: float = 3.0  # the second-best reference must be this much farther, else no tie
    min_extent_m: float = 1.0  # the normal "wobbles" by the construction accuracy over the patch size, at least this


@dataclasses.dataclass(frozen=True)
class ControlConfig:
    """``[control]``: control and check points the unit stood on (``--control``, ``--check``;
    :mod:`kinreg.estimate.control`)."""

    # The point of the unit that touches the control point, in the platform (trajectory) frame [m].
    reference_point_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # A stand-still: for at least min_still_s the reference point stays within max_radius_m of its
    # mean and the unit turns less than max_rotation_deg from its middle orientation, over every
    # window_s and over the whole stretch. A hand holding the unit on a point sways it by a few
    # cm/s over 1-2 cm per axis (up to 1.7 cm from the mean, 3 cm with the last centimetres of
    # the stop and the first of the start); slow walking (0.25 m/s) leaves a 4 cm ball within
    # 0.3 s, a turn on the spot turns tens of degrees in a window.
    min_still_s: float = 2.0
    max_radius_m: float = 0.04
    max_rotation_deg: float = 5.0
    window_s: float = 1.0
    gate_m: float = 0.5  # a point is assigned to the nearest stand-still within this distance ...
    ambiguity_ratio: float = 3.0  # ... if the second nearest is this much farther, else it is ambiguous
    # With one or two control points and no other datum, the rotations they leave free are held
    # at the first station's: the datum observation's standard deviation [rad] (tiny: a datum).
    free_rotation_sigma_rad: float = 1e-6
    # A target in a static scan: the scan's own standard deviation [mm] per axis of the target's
    # centre in its frame, added (in quadrature) to the row's survey sigma_mm. 2 mm: what a
    # terrestrial scanner's checkerboard or sphere target holds at 10-30 m (1-2 mm), taken high.
    target_sigma_mm: float = 2.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.target_sigma_mm) and self.target_sigma_mm >= 0):
            raise ConfigError(f"[control] target_sigma_mm: expected a number >= 0, got {self.target_sigma_mm!r}")
        for key in ("min_still_s", "max_radius_m", "max_rotation_deg", "window_s"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"[control] {key}: expected a number > 0, got {value!r}")
        r = self.reference_point_m
        if not isinstance(r, list | tuple) or len(r) != 3 or any(
                isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) for v in r):
            raise ConfigError(f"[control] reference_point_m: expected three numbers [x, y, z], got {r!r}")
        object.__setattr__(self, "reference_point_m", tuple(float(v) for v in r))


@dataclasses.dataclass(frozen=True)
class DiscontinuityConfig:
    """``[jumps]``: gross errors of the trajectory, found in the trajectory itself
    (:func:`kinreg.estimate.jumps.detect_jumps`). A jump (a SLAM failure: the trajectory steps by
    decimetres between two rows and carries the step on) is taken out of the stations' initial
    poses, of the trajectory links and of the corrected cloud and trajectory; the scan whose
    window contains it is not linked (its points were georeferenced on both sides of the step).
    ``detect = false`` leaves the trajectory as it is.

    An interval is a jump when its translation excess is at least ``min_step_m`` **and**
    ``k_sigma`` robust noise sigmas, or its rotation excess at least ``min_step_deg`` and
    ``k_sigma`` sigmas, under both clocks (see :mod:`kinreg.estimate.jumps`).

    - ``min_step_m = 0.05``: walking at 100 Hz changes the increment by well under a millimetre
      between samples; the largest excess of a clean interval is 0.1 mm on the simulated run and
      0.5 mm on the real GeoSLAM file for the index clock, 1.3 mm and 23 mm for the time clock (the
      real stamps jitter by 6 ms at 1-2 m/s). 5 cm keeps a factor of two over that worst case and
      is far below the decimetres of a SLAM failure; smaller steps are left to the block
      adjustment, whose trajectory links carry millimetres to centimetres.
    - ``min_step_deg = 1.0``: turns reach 200 deg/s (2 deg per sample), hand vibration on the real
      file 0.4 deg per sample at about 7 Hz; the largest excess of a clean interval is 0.0004 deg
      (simulated) and 0.24 deg (real) for the index clock, 0.08 and 0.56 deg for the time clock, so
      1 deg keeps a factor of four against false alarms on the real file (both clocks must pass);
      there a jump just above 1 deg can be missed (2 of 200 injected 1.2 deg jumps were).
    - ``k_sigma = 8``: the excesses are not Gaussian (step cycle, turns, vibration); the noise test
      only decides where a trajectory is so noisy that the floors sit inside its noise.
    - ``window_samples = 10`` per side (0.1 s at 100 Hz) for the medians and chords: long enough
      that the medians ignore a few neighbouring outliers (a jump and its return 3 samples later
      are both found), short enough to follow the motion.
    - ``fit_samples = 4`` per side for the quadratic of pass 2: 3 to 5 fit the real file's
      vibration to 0.1-0.2 deg, longer windows average it away (0.4 deg with 10).
    - ``scale_window_samples = 500`` (5 s at 100 Hz): blocks for the MAD; each interval takes the
      largest scale of its block and the two next to it, so a block of standing still does not
      make the start of walking look noise-free.
    """

    detect: bool = True
    window_samples: int = 10
    fit_samples: int = 4
    scale_window_samples: int = 500
    k_sigma: float = 8.0
    min_step_m: float = 0.05
    min_step_deg: float = 1.0


@dataclasses.dataclass(frozen=True)
class ReportConfig:
    """``[report]``: what ``report.html`` shows of the cloud (:mod:`kinreg.report.cloud_views`),
    gathered while ``corrected.laz`` is written."""

    cloud_views: bool = True  # sections and the plane-thickness map; false skips them
    # Heights (z in the cloud's frame, m) of the horizontal sections; empty: one height chosen
    # 1.0-1.5 m above the lowest floor of the first chunk of points.
    section_heights_m: tuple[float, ...] = ()
    section_band_m: float = 0.10  # thickness of the slab around each height
    section_pixel_m: float = 0.02  # raster resolution, coarser where the cloud is wider than ...
    section_max_px: int = 2000  # ... this many pixels
    thickness_cell_m: float = 1.0  # cube of the plane-thickness map (absolute grid)
    thickness_stride: int = 1  # every n-th point enters the thickness map (cheaper on big clouds)

    def __post_init__(self) -> None:
        heights = self.section_heights_m
        if not isinstance(heights, list | tuple) or any(isinstance(h, bool) or not isinstance(h, int | float)
                                                        for h in heights):
            raise ConfigError(f"[report] section_heights_m: expected a list of numbers, got {heights!r}")
        object.__setattr__(self, "section_heights_m", tuple(float(h) for h in heights))
        if self.section_max_px < 16 or self.thickness_stride < 1:
            raise ConfigError("[report] section_max_px must be at least 16 and thickness_stride at least 1")


@dataclasses.dataclass(frozen=True)
class KinregConfig:
    input: InputConfig = dataclasses.field(default_factory=InputConfig)
    slicing: SlicingConfig = dataclasses.field(default_factory=SlicingConfig)
    planes: PlanesConfig = dataclasses.field(default_factory=PlanesConfig)
    drift: DriftConfig = dataclasses.field(default_factory=DriftConfig)
    matching: MatchingConfig = dataclasses.field(default_factory=MatchingConfig)
    pairwise: PairwiseConfig = dataclasses.field(default_factory=PairwiseConfig)
    block: BlockConfig = dataclasses.field(default_factory=BlockConfig)
    static: StaticConfig = dataclasses.field(default_factory=StaticConfig)
    reference: ReferenceConfig = dataclasses.field(default_factory=ReferenceConfig)
    jumps: DiscontinuityConfig = dataclasses.field(default_factory=DiscontinuityConfig)
    control: ControlConfig = dataclasses.field(default_factory=ControlConfig)
    report: ReportConfig = dataclasses.field(default_factory=ReportConfig)


C = TypeVar("C")


def _field_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _coerce(value: Any, kind: Any, where: str) -> Any:
    if isinstance(kind, type) and issubclass(kind, enum.Enum):
        try:
            return kind(value)
        except ValueError:
            allowed = ", ".join(str(m.value) for m in kind)
            raise ConfigError(f"{where}: '{value}' is not one of {allowed}") from None
    origin = typing.get_origin(kind)
    if origin in (typing.Union, types.UnionType):
        return value
    if kind is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
        return value
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{where}: expected a finite number, got {value!r}")
        return float(value)
    if kind is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    return value


def _without_removed(values: Mapping[str, Any], where: str) -> dict[str, Any]:
    """``values`` without the keys of :data:`_REMOVED`: dropped with a warning where they hold the
    value that was off; :class:`ConfigError` where they ask for the removed behaviour."""
    kept = dict(values)
    for (section, key), (off, why) in _REMOVED.items():
        if section != where or key not in kept:
            continue
        value = kept.pop(key)
        if isinstance(value, bool) is not isinstance(off, bool) or value != off:
            raise ConfigError(f"[{where}] {key} was removed ({why}); delete the line")
        log.warning("[%s] %s was removed (%s); the line can be deleted", where, key, why)
    return kept


def _build_section(cls: type[C], values: Mapping[str, Any], where: str) -> C:
    hints = _field_types(cls)
    values = _without_removed(values, where)
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(values) - names)
    if unknown:
        raise ConfigError(f"[{where}]: unknown key(s) {', '.join(unknown)} (known: {', '.join(sorted(names))})")
    kwargs = {k: _coerce(v, hints[k], f"[{where}] {k}") for k, v in values.items()}
    section = cls(**kwargs)
    _check_section(section, where)
    return section


def _check_section(section: Any, where: str) -> None:
    for f in dataclasses.fields(section):
        v = getattr(section, f.name)
        positive = f.name.endswith(("_s", "_m", "_points")) and not f.name.startswith("min_")
        if f.metadata.get("signed"):
            continue
        if f.metadata.get("share"):
            if not 0.0 <= v <= 1.0:
                raise ConfigError(f"[{where}] {f.name}: must be a share from 0 to 1, got {v}")
            continue
        if f.metadata.get("allow_zero"):
            positive = False
            if isinstance(v, int | float) and v < 0:
                raise ConfigError(f"[{where}] {f.name}: must not be negative, got {v}")
        if positive and isinstance(v, int | float) and not v > 0:
            raise ConfigError(f"[{where}] {f.name}: must be positive, got {v}")
        if f.name.startswith("min_") and isinstance(v, int | float) and v < 0:
            raise ConfigError(f"[{where}] {f.name}: must not be negative, got {v}")


def config_from_mapping(data: Mapping[str, Any]) -> KinregConfig:
    """Build a config from nested mappings (sections of keys); missing keys keep defaults."""
    sections = {f.name: f for f in dataclasses.fields(KinregConfig)}
    hints = _field_types(KinregConfig)
    data = {k: v for k, v in data.items() if k != "schema_version"}
    unknown = sorted(set(data) - set(sections))
    if unknown:
        raise ConfigError(f"unknown section(s) {', '.join(unknown)} (known: {', '.join(sections)})")
    kwargs = {}
    for name in sections:
        values = data.get(name, {})
        if not isinstance(values, Mapping):
            raise ConfigError(f"[{name}] must be a table of keys")
        kwargs[name] = _build_section(hints[name], values, name)
    return KinregConfig(**kwargs)


def load_config(path: str | Path | None = None, overrides: Mapping[str, Any] | None = None) -> KinregConfig:
    """Defaults, updated by the TOML file at ``path`` (if any), then by ``overrides``.

    ``overrides`` maps ``"section.key"`` to a value (from the command line).
    Raises :class:`ConfigError` naming the file for syntax errors, unknown keys, bad values.
    """
    data: dict[str, Any] = {}
    if path is not None:
        p = Path(path)
        try:
            with open(p, "rb") as f:
                data = tomllib.load(f)
        except FileNotFoundError:
            raise ConfigError("file not found", p) from None
        except tomllib.TOMLDecodeError as e:
            raise ConfigError(f"invalid TOML: {e}", p) from None
        except RecursionError:
            raise ConfigError("invalid TOML: arrays or tables nested too deep", p) from None
        except (OSError, UnicodeDecodeError) as e:
            raise ConfigError(f"cannot read: {e}", p) from None
    for dotted, value in (overrides or {}).items():
        if value is None:
            continue
        section, _, key = dotted.partition(".")
        data.setdefault(section, {})[key] = value.value if isinstance(value, enum.Enum) else value
    try:
        return config_from_mapping(data)
    except ConfigError as e:
        raise ConfigError(e.reason, path) from None


def _toml_value(v: Any) -> str:
    if isinstance(v, enum.Enum):
        v = v.value
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return str(v)


def format_toml(config: KinregConfig) -> str:
    """The configuration as TOML text (readable back by :func:`load_config`)."""
    lines = [f"schema_version = {CONFIG_SCHEMA_VERSION}", ""]
    for section in dataclasses.fields(config):
        lines.append(f"[{section.name}]")
        values = getattr(config, section.name)
        for f in dataclasses.fields(values):
            lines.append(f"{f.name} = {_toml_value(getattr(values, f.name))}")
        lines.append("")
    return "\n".join(lines)
