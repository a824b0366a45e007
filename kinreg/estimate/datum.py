"""The datum of the block adjustment and the network it is adjusted in: static scans (fixed or
observed), reference planes (tie planes), or else the first station (METHOD.md section 2, steps 7-9);
and trajectory jumps taken out of the stations before they are linked."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence

import numpy as np

from kinreg.config import BlockConfig, Disconnected, DiscontinuityConfig, KinregConfig, StaticConfig, StaticDatum
from kinreg.errors import ConfigError, EstimationError
from kinreg.estimate.block import adjust_block, loose_parts
from kinreg.estimate.control import (
    ControlTie,
    control_covariance,
    control_observations,
    first_station_rotation,
    free_rotations,
)
from kinreg.estimate.drift import DriftRates, with_window_deformation
from kinreg.estimate.frames import adjust_with_frames, extra_first, window_gain
from kinreg.estimate.jumps import detect_jumps, jump_arrays, jump_removal
from kinreg.estimate.network import Datum, Network, block_observations
from kinreg.estimate.plane_nodes import plane_node_observations
from kinreg.estimate.reference import associate, tie_observations
from kinreg.estimate.snooping import chi2_quantile
from kinreg.geometry import Pose, pose_sigmas, skew
from kinreg.progress import Progress
from kinreg.survey import ReferencePlanes
from kinreg.types import (
    BlockResult,
    Link,
    LinkStatus,
    ObservationKind,
    Plane,
    RelativeObservation,
    ScanKind,
    Station,
    Tie,
    Trajectory,
    TrajectoryJump,
)

log = logging.getLogger(__name__)


def take_out_jumps(
    stations: list[Station], planes: list[tuple[Plane, ...]], trajectory: Trajectory, config: DiscontinuityConfig,
) -> tuple[list[Station], list[tuple[Plane, ...]], list[TrajectoryJump]]:
    """Find jumps in the trajectory (:func:`~kinreg.estimate.jumps.detect_jumps`) and take them out
    of the quasi-static stations' initial poses, so that the trajectory links and the pairwise
    priors no longer carry them. A scan's points are in its own frame whatever the trajectory
    did, except where its window contains a jump: those points were georeferenced on both sides
    of the step, so that scan keeps only its trajectory links (its planes are dropped). The
    corrected cloud and trajectory take the jumps out by time (:class:`DriftCorrection`)."""
    if not config.detect:
        return stations, planes, []
    jumps = detect_jumps(trajectory, config)
    if not jumps:
        return stations, planes, []
    intervals, steps = jump_arrays(jumps)
    times = np.array([s.t_s for s in stations])
    quasi = np.flatnonzero([s.kind is ScanKind.QUASI_STATIC for s in stations])
    removal = jump_removal(intervals, steps, times[quasi])
    stations, planes = list(stations), list(planes)
    for n, k in enumerate(quasi):
        s = stations[k]
        stations[k] = dataclasses.replace(s, T_obj_scan=removal[n].compose(s.T_obj_scan))
        inside = [j.t_s for j in jumps if s.t_start_s < j.t_s and j.t_before_s < s.t_end_s]
        if inside:
            log.warning("scan %s contains the trajectory jump at %.2f s: not linked by planes", s.name, inside[0])
            planes[k] = ()
    for j in jumps:
        log.warning("the trajectory jumps by %.3f m and %.2f deg at %.3f s (row %d): taken out "
                    "(set [jumps] detect = false to keep it)", j.step_m, j.step_deg, j.t_s, j.index)
    return stations, planes, jumps


def _axis_name(v: np.ndarray) -> str:
    k = int(np.argmax(np.abs(v)))
    return "xyz"[k] if abs(v[k]) > 0.99 else "(" + ", ".join(f"{c:.2f}" for c in v) + ")"


def free_static_directions(stations: Sequence[Station], links: Sequence[Link], holding: Sequence[int],
                           sigma_m: float = 0.05, sigma_deg: float = 0.05) -> list[str]:
    """The directions, in words, that the plane links between the static stations ``holding`` (they
    hold the datum) and all other stations leave nearly free: where their summed information
    (object axes, each link's turned by its second station's rotation) is below ``1 / sigma^2`` for
    a translation or a rotation. A static scan in a corridor sees no plane across it: alone, it
    leaves the translation along the corridor to nothing."""
    held = set(holding)
    info = np.zeros((6, 6))
    for link in links:
        if link.status is not LinkStatus.OK or link.rank == 0 or (link.scan_i in held) == (link.scan_j in held):
            continue
        B = np.kron(np.eye(2), stations[link.scan_j].T_obj_scan.rotation_matrix)
        info += B @ link.info_planes @ B.T
    words = []
    for block, floor, what in ((slice(0, 3), sigma_m**-2, "translation along"),
                               (slice(3, 6), np.radians(sigma_deg) ** -2, "rotation about")):
        w, V = np.linalg.eigh(0.5 * (info[block, block] + info[block, block].T))
        words += [f"{what} {_axis_name(V[:, k])}" for k in range(3) if w[k] < floor]
    return words


def _check_reference_datum(ties: list[Tie], references: ReferencePlanes) -> None:
    """The tied reference planes must fix all six datum directions: normals spanning three
    directions fix the translations (and then the rotations too)."""
    normals = references.normals[sorted({t.reference for t in ties})]
    _, sing, Vt = np.linalg.svd(normals)
    free = [Vt[k] for k in range(3) if k >= len(sing) or sing[k] < 0.1]
    if free:
        directions = " and ".join(f"translation along {_axis_name(v)}" for v in free)
        if len(free) == 2:
            directions += f", rotation about {_axis_name(normals[0])}"
        raise ConfigError(f"the tied reference planes do not fix the datum: {directions} stay free; add reference "
                          "planes in that direction, [[link]] entries, or static scans", references.source)


def build_network(
    stations: Sequence[Station],
    planes: Sequence[tuple[Plane, ...]],
    links: Sequence[Link],
    references: ReferencePlanes | None,
    static: StaticConfig | None,
    config: KinregConfig,
    controls: Sequence[ControlTie] = (),
) -> Network:
    """The network the block adjusts, with its datum: static scans (fixed, or observed with
    ``[static] sigma_*``), reference planes (a tie plane per detected plane on one), or else the
    first station. Control points (``controls``) join any of these; alone, three or more (not on
    one line) are the datum, and the rotations that one or two leave free are held at the first
    station's. A static scan with control targets is held by its targets, not by ``static``; with
    targets, ``static.datum = "fixed"`` holds no static scan: those without targets keep their
    pose as an observation with ``static.prior_sigma_*`` (``"observed"``: ``static.sigma_*``). A
    part of the network that no link ties to the datum is refused, or (``[block] disconnected =
    "fix_each"``) held on its own first station. Raises :class:`ConfigError` when the reference
    planes tie nothing or leave a datum direction free, :class:`EstimationError` when the network
    falls apart."""
    poses_initial = Pose.stack([s.T_obj_scan for s in stations])
    is_static = np.array([s.kind is ScanKind.STATIC for s in stations])
    fixed = np.zeros(len(stations), dtype=bool)
    datum_obs: list[RelativeObservation] = []
    ties: list[Tie] = []
    datum: list[str] = []
    # A static scan with control targets is held by them (its E57 pose is only the start). With
    # targets, no static scan is held fixed at its E57 pose: the targets are the datum, and a scan
    # fixed where its registration put it would compete with the survey (a scan 2 cm off had good
    # targets and stand-still points rejected in its place). The others keep their E57 pose as a
    # weak observation (the static prior, [static] prior_sigma_*), for the directions their planes
    # leave free (a scan in a corridor floated 2 m along it without); "observed" observes them.
    targeted = sorted({t.station for t in controls if t.target})
    is_static[targeted] = False
    unfixed = ""  # said after the datum (it is none)
    if targeted and static is not None and static.datum is StaticDatum.FIXED and is_static.any():
        unfixed = (f"static scans without targets not fixed (held by their planes, their E57 poses observed with "
                   f"{static.prior_sigma_m:g} m / {static.prior_sigma_deg:g} deg)")
        prior_sigma = pose_sigmas(static.prior_sigma_m, np.radians(static.prior_sigma_deg))
        datum_obs += [RelativeObservation(ObservationKind.STATION, int(k), -1, stations[int(k)].T_obj_scan,
                                          np.diag(1.0 / prior_sigma**2), 6) for k in np.flatnonzero(is_static)]
        is_static[:] = False
    if static is not None and is_static.any():
        if static.datum is StaticDatum.FIXED:
            fixed |= is_static
            datum.append("static scans fixed")
        else:
            sigma = pose_sigmas(static.sigma_mm / 1000.0, np.radians(static.sigma_mdeg / 1000.0))
            datum_obs += [RelativeObservation(ObservationKind.STATION, int(k), -1, stations[int(k)].T_obj_scan,
                                              np.diag(1.0 / sigma**2), 6) for k in np.flatnonzero(is_static)]
            datum.append("static scans observed")
    if references is not None:
        ties = associate([s.name for s in stations], poses_initial, planes, references, config.reference)
        if not ties:
            raise ConfigError("no detected plane could be tied to a reference plane (is the trajectory in the "
                              "building's frame? give [initial_transform] or [[link]] entries otherwise)",
                              references.source)
        datum_obs += tie_observations(ties, poses_initial, planes, references, config.reference)
        datum.append(f"reference planes ({len(ties)} tie planes)")
    if controls:
        axes, fixes = free_rotations(controls)
        if not datum and len(axes):
            datum_obs.append(first_station_rotation(axes, 0, stations[0].T_obj_scan,
                                                    config.control.free_rotation_sigma_rad))
            fixes += f"; the first station's rotation about {'every axis' if len(axes) == 3 else 'that line'}"
        n_targets = sum(t.target for t in controls)
        on = (f", {n_targets} of them targets in static scan(s) {', '.join(stations[k].name for k in targeted)}"
              if n_targets else "")
        datum.append(f"{len(controls)} control point(s){on} (fixing {fixes})")
        if n_targets == len(controls) and references is None:
            # The targets hold their static scans; the rest of the network hangs on those scans' links.
            holding = targeted + [int(k) for k in np.flatnonzero(is_static)]
            free = free_static_directions(stations, links, holding)
            if free:
                log.warning("the static scans that hold the datum (%s) are linked to the other scans by planes that "
                            "leave the %s nearly free (sigma above 5 cm or 0.05 deg): the stations' sigmas show "
                            "it; add targets on a static scan that sees planes across it, or stand-still control "
                            "points", ", ".join(stations[k].name for k in holding), " and ".join(free))
                datum.append(f"{' and '.join(free)} nearly free (the static scans' links)")
        if unfixed:
            datum.append(unfixed)
    if not datum:
        fixed[0] = True
        datum.append("first station")
    if references is not None and not fixed.any() and static is None and not controls:
        _check_reference_datum(ties, references)
    prior = DriftRates.from_config(config.drift)
    parts = loose_parts(block_observations(stations, links, prior) + datum_obs
                        + control_observations(controls, stations, prior), fixed, len(stations))
    if parts:
        names = ", ".join(f"{stations[p[0]].name}..{stations[p[-1]].name}" for p in parts[:5])
        if config.block.disconnected is Disconnected.STOP:
            raise EstimationError(
                f"the network falls apart: {len(parts)} part(s) are not linked to the datum ({names}); set "
                '[block] disconnected = "fix_each" to adjust each part in its own datum')
        log.warning("%d part(s) not linked to the datum (%s): each adjusted with its first station fixed",
                    len(parts), names)
        for p in parts:
            fixed[p[0]] = True
        datum.append(f"{len(parts)} disconnected part(s) each on its first station")
    return Network(tuple(stations), tuple(links), Datum(fixed, tuple(datum_obs), "; ".join(datum), tuple(ties),
                                                        tuple(controls)),
                   np.array([window_gain(p) for p in planes]).reshape(-1, 6, 6))


def screen_control_points(network: Network, rates: DriftRates, config: BlockConfig, progress: Progress,
                          previous: BlockResult | None = None) -> Network:
    """``network`` without the control points that do not fit the others (kept in
    ``datum.rejected_controls`` with their normalised residual).

    Each point is tested against the network adjusted without it (no variance components, no data
    snooping): ``T = d^T (C + J Q J^T)^-1 d``, chi-square with 3 degrees of freedom, where ``d`` is
    the predicted minus the surveyed position, ``C`` its observation's covariance and ``J Q J^T``
    the prediction's. The worst point above the critical value (``[block] alpha``) goes, and the
    rest are tested again. A rejection that would leave the datum short of a direction (fewer than
    three points off one line, and nothing else to hold it) is not made.

    Why not the block's own snooping: it estimates a variance component per observation kind,
    and one wrong point among four inflated theirs until it no longer stood out (a point 5 cm off
    at a normalised residual of 1.4 on a simulated run); it takes out every observation above the
    critical value on separate stations in one round, so all control points at once; and a point
    that alone carries some direction (a weak geometry) is never rejected there, so a good point
    was rejected in place of the wrong one."""
    if not network.datum.controls or not config.data_snooping or len(network.datum.controls) < 2:
        return network
    plain = dataclasses.replace(config, variance_components=False, data_snooping=False)
    held_elsewhere = bool(network.datum.fixed.any() or network.datum.observations)
    critical = chi2_quantile(1.0 - config.alpha, 3)
    rejected: list[tuple[str, float]] = []
    while len(rejected) < config.max_rejections:
        controls = network.datum.controls
        scores = {}
        for k in range(len(controls)):
            others = controls[:k] + controls[k + 1:]
            if not held_elsewhere and len(free_rotations(others)[0]):
                continue  # without it the rest would not hold the datum: it cannot be tested against them
            without = dataclasses.replace(network, datum=dataclasses.replace(network.datum, controls=others))
            result = adjust_network(without, rates, plain, progress, previous)
            scores[k] = _leave_one_out(controls[k], result, network, rates, not config.scan_frames)
        worst = max(scores, key=lambda k: scores[k], default=None)
        if worst is None or not scores[worst] > critical:
            break
        name = controls[worst].name
        normalised = float(np.sqrt(scores[worst] / 3.0))
        log.warning("control point %s%s rejected: it does not fit the network and the other control points "
                    "(normalised residual %.1f against its sigma)", name,
                    f" (target in static scan {network.stations[controls[worst].station].name})"
                    if controls[worst].target else "", normalised)
        rejected.append((name, normalised))
        network = dataclasses.replace(network, datum=dataclasses.replace(
            network.datum, controls=controls[:worst] + controls[worst + 1:]))
    if not rejected:
        return network
    names = ", ".join(name for name, _ in rejected)
    datum = dataclasses.replace(network.datum, description=f"{network.datum.description}; control point(s) {names} "
                                "rejected", rejected_controls=network.datum.rejected_controls + tuple(rejected))
    return dataclasses.replace(network, datum=datum)


def _leave_one_out(tie: ControlTie, result: BlockResult, network: Network, rates: DriftRates,
                   window_bias: bool) -> float:
    """The test statistic of control point ``tie`` against ``result`` (adjusted without it)."""
    C = control_covariance(tie, network.stations, rates, result, window_bias)
    d = tie.predicted(result.poses) - tie.xyz
    # The prediction's covariance: the blend of the two stations' (an upper bound whatever their
    # correlation, which the block result does not keep: Var((1-s) a + s b) <= (1-s) Var a + s Var b).
    prediction = (1.0 - tie.share) * _predicted_covariance(tie.station, tie.q_scan, result)
    if tie.other >= 0:
        prediction += tie.share * _predicted_covariance(tie.other, tie.q_other, result)
    return float(d @ np.linalg.solve(C + prediction, d))


def _predicted_covariance(k: int, q: np.ndarray, result: BlockResult) -> np.ndarray:
    """The covariance (3, 3) of the point ``q`` of station ``k``'s scan frame, from ``result``."""
    J = result.poses[k].rotation_matrix @ np.hstack([np.eye(3), -skew(q)])
    return J @ result.cov_xi[k] @ J.T


def adjust_network(network: Network, rates: DriftRates, config: BlockConfig, progress: Progress,
                   previous: BlockResult | None = None) -> BlockResult:
    """The block adjustment of ``network`` (:func:`~kinreg.estimate.block.adjust_block`), its
    trajectory links weighted by ``rates`` and coupled through a ``previous`` adjustment; with
    ``[block] scan_frames``, with a scan frame and a sensor pose per quasi-static station
    (:mod:`kinreg.estimate.frames`)."""
    if config.scan_frames:
        observations = network.observations(rates, previous, window_bias=False)
        extra = None
        if network.planes is not None and network.plane_nodes is not None:
            # the physical planes as nodes (after the controls: their indices stay)
            cov = network.velocity_cov
            # with the surfaces' departure the links measured (the planes' own covariances know only
            # their points' noise)
            deformed = [with_window_deformation(network.link_model.apply(p), s.T_obj_scan, rates,
                                                None if cov is None else cov[k])
                        for k, (s, p) in enumerate(zip(network.stations, network.planes, strict=True))]
            extra, by_plane = plane_node_observations(network.initial_poses, deformed, network.plane_nodes,
                                                      extra_first(network.stations))
            observations += by_plane
        return adjust_with_frames(network.stations, network.initial_poses, observations, network.datum.fixed, rates,
                                  config, progress, network.window_gain, network.velocity_cov, extra)
    return adjust_block(network.initial_poses, network.observations(rates, previous), network.datum.fixed, config,
                        progress)
