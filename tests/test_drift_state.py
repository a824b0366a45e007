"""The trajectory's drift as a correlated process (issue #14): the block carries the drift
velocity of every trajectory link as an unknown (first-order Gauss-Markov), and the correlation
time is measured from the first adjustment's corrections."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from kinreg.config import BlockConfig, MatchingConfig
from kinreg.estimate.block import adjust_block
from kinreg.estimate.drift import DriftRates, estimate_drift_rates
from kinreg.estimate.network import block_observations
from kinreg.geometry import Pose
from kinreg.types import ObservationKind, RelativeObservation, ScanKind, Station

N_STATIONS, DT = 30, 6.0
SIGMA_V = np.array([3e-4, 3e-4, 1e-4, 2e-6, 2e-6, 1e-5])  # drift velocity spread per object axis
FLOOR_M, FLOOR_RAD = 2e-4, 2e-6
PLANE_SIGMA = np.array([3e-4, 3e-4, 3e-4, 3e-5, 3e-5, 3e-5])


def _walk() -> Pose:
    t = DT * np.arange(N_STATIONS)
    yaw = 0.02 * t  # a gentle turn: the stations' axes differ from the object's
    quat = np.column_stack([np.cos(yaw / 2), 0 * t, 0 * t, np.sin(yaw / 2)])
    return Pose(quat, np.column_stack([0.8 * t, 5.0 * np.sin(0.01 * t), 0 * t]))


def _network(seed: int, tau_s: float):
    """A walk whose first 8 stations see common planes (links among them) and whose other 22 are
    carried by the trajectory alone; the drift velocity a Gauss-Markov process with ``tau_s``."""
    rng = np.random.default_rng(seed)
    truth = _walk()
    decay = np.exp(-DT / tau_s)
    v = np.zeros((N_STATIONS - 1, 6))
    v[0] = rng.normal(0.0, SIGMA_V)
    for k in range(1, N_STATIONS - 1):
        v[k] = decay * v[k - 1] + rng.normal(0.0, SIGMA_V * np.sqrt(1.0 - decay**2))
    floor = np.array([FLOOR_M] * 3 + [FLOOR_RAD] * 3)
    poses = [truth[0]]
    for k in range(N_STATIONS - 1):
        rel = truth[k].inverse().compose(truth[k + 1])
        S = np.kron(np.eye(2), truth[k + 1].rotation_matrix.T)
        error = DT * S @ v[k] + rng.normal(0.0, floor)
        poses.append(poses[-1].compose(rel.compose(Pose.exp(-error))))
    initial = Pose.stack(poses)
    stations = [Station(k, f"s{k}", ScanKind.QUASI_STATIC, DT * k, DT * k, DT * k, initial[k], 1000, tau_s=0.0)
                for k in range(N_STATIONS)]
    planes = []
    for a in range(8):
        for b in range(a + 1, 8):
            Z = truth[a].inverse().compose(truth[b]).compose(Pose.exp(rng.normal(0.0, PLANE_SIGMA)))
            planes.append(RelativeObservation(ObservationKind.PLANES, a, b, Z, np.diag(PLANE_SIGMA**-2), 6))
    return truth, stations, planes


def _normalised_errors(tau_model: float, seeds=range(40)) -> np.ndarray:
    rates = DriftRates(SIGMA_V[:3], SIGMA_V[3:], FLOOR_M, FLOOR_RAD, correlation_s=(tau_model, tau_model))
    fixed = np.zeros(N_STATIONS, dtype=bool)
    fixed[0] = True
    z = []
    for seed in seeds:
        truth, stations, planes = _network(seed, tau_s=120.0)
        observations = planes + block_observations(stations, [], rates)
        result = adjust_block(Pose.stack([s.T_obj_scan for s in stations]), observations, fixed,
                              BlockConfig(data_snooping=False, variance_components=False))
        assert not result.failed
        error = result.poses.t_xyz[1:] - truth.t_xyz[1:]
        z.append(error / result.sigma_position_m[1:])
    return np.concatenate(z)


def test_a_smooth_drift_carried_by_the_trajectory_alone_gets_honest_sigmas():
    """22 stations beyond the planes, drift velocity correlated over 120 s: with the drift as a
    process the errors follow their sigmas (pooled RMS per axis near 1); taken as independent from
    link to link, the same sigmas are several times too small where the trajectory alone carries."""
    z = _normalised_errors(120.0)
    rms = np.sqrt(np.mean(z**2, axis=0))
    assert np.all((rms > 0.8) & (rms < 1.25)), rms
    z_independent = _normalised_errors(1e-9)
    assert np.sqrt(np.mean(z_independent**2)) > 1.5 * np.sqrt(np.mean(z**2))


def test_the_drift_velocity_learnt_on_the_planes_carries_on_beyond_them():
    """Where planes fix the first stations, their drift velocity is known and, correlated, goes on:
    the stations beyond are corrected better than by independent links."""
    def error(tau_model):
        rates = DriftRates(SIGMA_V[:3], SIGMA_V[3:], FLOOR_M, FLOOR_RAD, correlation_s=(tau_model, tau_model))
        out = []
        for seed in range(20):
            truth, stations, planes = _network(seed, tau_s=120.0)
            fixed = np.arange(N_STATIONS) == 0
            result = adjust_block(Pose.stack([s.T_obj_scan for s in stations]),
                                  planes + block_observations(stations, [], rates), fixed,
                                  BlockConfig(data_snooping=False, variance_components=False))
            out.append(np.linalg.norm(result.poses.t_xyz[8:16] - truth.t_xyz[8:16], axis=1))
        return np.sqrt(np.mean(np.square(out)))

    assert error(120.0) < 0.8 * error(1e-9)


def test_independent_links_add_no_unknowns():
    """Without a correlation the block's observations are those of independent links."""
    truth, stations, planes = _network(0, tau_s=120.0)
    rates = DriftRates(SIGMA_V[:3], SIGMA_V[3:], FLOOR_M, FLOOR_RAD)
    kinds = {o.kind for o in block_observations(stations, [], rates)}
    assert kinds == {ObservationKind.TRAJECTORY}
    rates = replace(rates, correlation_s=(60.0, 60.0))
    observations = block_observations(stations, [], rates)
    drift = [o for o in observations if o.kind is ObservationKind.DRIFT]
    assert len(drift) == N_STATIONS - 1  # a prior for the first link, a tie for each next one
    assert sum(o.j < 0 for o in drift) == 1


def _stations(n: int) -> list[Station]:
    walk = Pose(np.tile([1.0, 0, 0, 0], (n, 1)), np.column_stack([0.5 * DT * np.arange(n), np.zeros(n), np.zeros(n)]))
    return [Station(k, f"s{k}", ScanKind.QUASI_STATIC, DT * k, DT * k - 3, DT * k + 3, walk[k], 1000)
            for k in range(n)]


@pytest.mark.parametrize(("smooth", "expect_long"), [(True, True), (False, False)])
def test_the_correlation_time_is_measured_from_the_corrections(smooth, expect_long):
    n = 60
    stations = _stations(n)
    walk = Pose.stack([s.T_obj_scan for s in stations])
    rng = np.random.default_rng(3)
    if smooth:  # a drift velocity that turns slowly
        t = DT * np.arange(n)
        velocity = 3e-4 * np.column_stack([np.cos(t / 200.0), np.sin(t / 200.0), 0 * t])
    else:  # a new velocity every link
        velocity = rng.normal(0.0, 3e-4, (n, 3))
    shift = np.vstack([np.zeros(3), np.cumsum(velocity[:-1] * DT, axis=0)])
    drifted = Pose(walk.quat_wxyz, walk.t_xyz + shift)
    result = SimpleNamespace(poses=drifted, poses_initial=walk, tests=(), cov_xi=np.zeros((n, 6, 6)))
    prior = DriftRates(np.full(3, 3e-4), np.full(3, 5e-5), 1e-3, 1e-4)
    tau_pos, _ = estimate_drift_rates(stations, result, prior).correlation_s
    if expect_long:
        assert tau_pos > 100.0
    else:
        assert tau_pos < DT


def test_the_stations_own_noise_does_not_shorten_the_correlation_time():
    """A drift velocity that turns over minutes, read off stations with 1 mm of noise each (the
    velocities' noise 1.7 times the drift's): with the noise the adjustment reports taken out of
    the squares, the correlation stays long; counted as drift, it would read as a few seconds."""
    from kinreg.estimate.drift import _correlation_times

    n = 200
    t = DT * np.arange(n)
    true_v = 3e-4 * np.column_stack([np.cos(t / 300.0), np.sin(t / 300.0), 0.5 + 0 * t])
    station_noise = np.random.default_rng(5).normal(0.0, 1e-3, (n + 1, 3))
    v = true_v + np.diff(station_noise, axis=0) / DT
    ends = [(k, k + 1) for k in range(n)]
    noise = np.full((n, 3), 2e-6 / DT**2)
    tau_with, _ = _correlation_times(ends, np.full(n, DT), v, v, noise, noise)
    tau_without, _ = _correlation_times(ends, np.full(n, DT), v, v)
    assert tau_with > 100.0
    assert tau_without < 20.0


def test_a_trajectory_link_far_off_its_model_is_named(caplog):
    """The trajectory's links are never rejected; one far beyond its model is named in a warning."""
    import logging

    from kinreg.estimate.strategy import _warn_trajectory_misfits
    from kinreg.types import ObservationTest

    def test(k, statistic):
        return ObservationTest(k, ObservationKind.TRAJECTORY, k, k + 1, statistic, 6, 3.0,
                               float(np.sqrt(statistic / 6)), False)

    quiet = SimpleNamespace(tests=[test(k, 6.0) for k in range(40)])
    with caplog.at_level(logging.WARNING):
        assert _warn_trajectory_misfits(quiet, 0.001, MatchingConfig()) == ([], [])
    assert not caplog.records
    loud = SimpleNamespace(tests=[test(k, 6.0) for k in range(40)] + [test(17, 6 * 81.0)])
    with caplog.at_level(logging.WARNING):
        misfits, wrong = _warn_trajectory_misfits(loud, 0.001, MatchingConfig())
    assert [t.i for t in misfits] == [t.i for t in wrong] == [17]  # no residual known: it may be a wrong match
    assert "17-18 (9 sigma)" in caplog.text and "Check the links there" in caplog.text
    caplog.clear()
    # 3 mm off: less than two distinct planes lie apart, the drift model's misfit, not a wrong match
    small = replace(test(17, 6 * 81.0), residual=np.array([0.003, 0.0, 0.0, 0.0, 0.0, 0.0]))
    with caplog.at_level(logging.WARNING):
        misfits, wrong = _warn_trajectory_misfits(SimpleNamespace(tests=[*quiet.tests, small]), 0.001,
                                                  MatchingConfig())
    assert [t.i for t in misfits] == [17] and wrong == []
    assert "17-18 (9 sigma, 3.0 mm), by less than a wrong plane match would" in caplog.text


def test_a_coupled_attitude_error_is_taken_out_of_the_planes():
    """GNSS/INS-like: a plane seen 2 s after the centre of a window walked at 0.5 m/s along x,
    with an attitude correction of 5 mrad about z, is off by R^T (phi x v tau) = 5 mm along y;
    deskewed with kappa = 1 it moves back by that, with kappa = 0 not at all."""
    from dataclasses import replace as replaced

    from planefixtures import plane_in_scan

    from kinreg.estimate.drift import deskewed_planes

    n = 3
    initial = Pose(np.tile([1.0, 0, 0, 0], (n, 1)), np.column_stack([0.5 * DT * np.arange(n), 4 + 0 * np.arange(n),
                                                                      1.5 + 0 * np.arange(n)]))
    stations = [Station(k, f"s{k}", ScanKind.QUASI_STATIC, DT * k, DT * k - 3, DT * k + 3, initial[k], 1000)
                for k in range(n)]
    adjusted = Pose.exp(np.array([0, 0, 0, 0, 0, 0.005])).compose(initial)
    adjusted = Pose(adjusted.quat_wxyz, initial.t_xyz)  # turned in place: the attitude corrected
    wall = plane_in_scan((0, 1, 0), 0.0, (6, 0, 1.5), (6, 1.5), initial[1], 1, 0, 1e-4, 1e-4, None)
    wall = replaced(wall, t_offset_s=2.0)
    planes = [(), (wall,), ()]
    result = SimpleNamespace(poses=adjusted, poses_initial=initial, cov_xi=np.zeros((n, 6, 6)))
    rates = DriftRates(SIGMA_V[:3], SIGMA_V[3:], FLOOR_M, FLOOR_RAD, coupling=1.0)
    out, largest = deskewed_planes(stations, planes, result, rates)
    assert largest == pytest.approx(0.005, rel=1e-2)
    assert out[1][0].d_m - wall.d_m == pytest.approx(-wall.normal @ np.array([0, 0.005, 0]), abs=1e-5)
    # Without coupling (SLAM-like), one rigid turn of the whole network moves no plane; with it,
    # the turn is an attitude error that turned the step (the same 5 mm).
    turned = Pose.exp(np.array([0, 0, 0, 0, 0, 0.005])).compose(initial)
    result = SimpleNamespace(poses=turned, poses_initial=initial, cov_xi=np.zeros((n, 6, 6)))
    out, largest = deskewed_planes(stations, planes, result, replace(rates, coupling=0.0))
    assert largest < 1e-9
    out, largest = deskewed_planes(stations, planes, result, rates)
    assert largest == pytest.approx(0.005, rel=1e-2)


@pytest.mark.parametrize("kappa", [0.0, 0.6, 1.0])
def test_the_jacobians_of_a_coupled_trajectory_link_match_finite_differences(kappa):
    """A trajectory link whose translation is partly the object-frame step turned by the first
    station's own (adjusted) attitude: its Jacobians against finite differences."""
    from kinreg.estimate import block

    rng = np.random.default_rng(7)
    poses = Pose.exp(rng.normal(0.0, [1.0, 1.0, 0.2, 0.1, 0.1, 0.8], (2, 6)))
    Z = poses[0].inverse().compose(poses[1]).compose(Pose.exp(rng.normal(0.0, 0.01, 6)))
    observation = RelativeObservation(ObservationKind.TRAJECTORY, 0, 1, Z, np.eye(6), 6, coupling=kappa,
                                      step_obj=poses[1].t_xyz - poses[0].t_xyz + rng.normal(0.0, 0.01, 3))
    weights = {k.value: 1.0 for k in ObservationKind}
    active = block._arrays([observation], np.ones(1, dtype=bool), -np.ones(2, dtype=int), weights)
    velocity = np.zeros((0, 6))
    e0, J = block._linearise(poses, velocity, active)
    for node in (0, 1):
        numeric = np.zeros((6, 6))
        for axis in range(6):
            step = np.zeros((2, 6))
            step[node, axis] = 1e-7
            e1, _ = block._linearise(poses.compose(Pose.exp(step)), velocity, active, jacobians=False)
            numeric[:, axis] = (e1[0] - e0[0]) / 1e-7
        scale = max(1.0, np.abs(numeric).max())
        assert np.allclose(J[0, node], numeric, atol=2e-2 * scale), (node, J[0, node], numeric)


def _coupling_case(model: str, noise_rad: float, seed: int = 0):
    """A walk with a growing heading error, drifted as ``model`` ("gnss": positions right, attitude
    off; "slam": the whole walk turned with it), plane links of each station to its next two with
    the true relative poses, and an adjustment that found the true poses up to ``noise_rad`` of
    heading per station."""
    from kinreg.types import Link, LinkStatus

    rng = np.random.default_rng(seed)
    n = 30
    t = 6.0 * np.arange(n)
    yaw = 0.4 * np.sin(t / 40.0)
    truth = Pose(np.column_stack([np.cos(yaw / 2), 0 * t, 0 * t, np.sin(yaw / 2)]),
                 np.column_stack([10 * np.cos(t / 40.0), 8 * np.sin(t / 30.0), 0 * t]))
    heading = np.radians(0.4) * t / t[-1]  # the attitude error D(t), about z
    D = Pose.exp(np.column_stack([np.zeros((n, 5)), heading]))
    if model == "gnss":
        xyz = truth.t_xyz
    else:  # dead reckoning: each step turned by the attitude error at its start
        steps = np.einsum("nij,nj->ni", D.rotation_matrix[:-1], np.diff(truth.t_xyz, axis=0))
        xyz = truth.t_xyz[0] + np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])
    initial = Pose(D.compose(truth).quat_wxyz, xyz)
    found = truth.compose(Pose.exp(np.column_stack([np.zeros((n, 5)), noise_rad * rng.standard_normal(n)])))
    stations = [Station(k, f"s{k}", ScanKind.QUASI_STATIC, t[k], t[k] - 3, t[k] + 3, initial[k], 1000)
                for k in range(n)]
    info = np.diag(1.0 / np.square([5e-4, 5e-4, 5e-4, 5e-5, 5e-5, 5e-5]))
    links = []
    for i in range(n):
        for j in (i + 1, i + 2):
            if j < n:
                rel = truth[i].inverse().compose(truth[j])
                links.append(Link(i, j, LinkStatus.OK, rel, np.linalg.inv(info), rel, rel, info, 6, np.zeros(6), 3,
                                  1.0, 10, True, (), (), 0.0, t[j] - t[i]))
    cov = np.zeros((n, 6, 6))
    cov[:, 3:, 3:] = np.eye(3) * noise_rad**2
    result = SimpleNamespace(poses=found, poses_initial=initial, tests=(), cov_xi=cov)
    return stations, links, result


@pytest.mark.parametrize(("model", "expected"), [("gnss", 1.0), ("slam", 0.0)])
def test_the_coupling_is_read_off_the_planes_own_steps(model, expected):
    """GNSS/INS-like (the object-frame step right, the attitude error turns it in the scan's
    frame) reads 1, SLAM-like (the whole walk turned with the heading) 0, from the planes' relative
    poses; with the adjusted heading 1 mrad off per station, the noise of the attitude does not
    pull the coupling towards 0 (without the correction it reads 0.87-0.92 here)."""
    from kinreg.estimate.drift import coupling_from_links

    prior = DriftRates(np.full(3, 3e-4), np.full(3, 5e-5), 1e-3, 1e-4)
    for noise in (0.0, 1e-3):
        stations, links, result = _coupling_case(model, noise)
        kappa = coupling_from_links(stations, links, result, prior)
        assert kappa == pytest.approx(expected, abs=0.05 if noise else 1e-3)
    stations, links, result = _coupling_case(model, 0.0)
    assert coupling_from_links(stations, links[:4], result, prior) is None  # too few links to say


def test_the_coupling_settles_where_it_measures_itself():
    """Planes deskewed with a coupling lean towards it: the measured coupling lies between the
    used one and the run's own. The secant over two rounds lands on the fixed point; a fixed point
    that names a regime is that regime's (0.9: GNSS/INS-like, 1), a mixed one is kept."""
    from kinreg.estimate.strategy import _settled_coupling

    for own, expected in ((0.9, 1.0), (0.5, 0.5)):
        def measured(used, own=own):
            return 0.5 * used + 0.5 * own

        tried = [(0.2, measured(0.2))]
        assert _settled_coupling(tried) == pytest.approx(measured(0.2))  # mixed: as measured
        tried.append((measured(0.2), measured(measured(0.2))))
        assert _settled_coupling(tried) == pytest.approx(expected)
    assert _settled_coupling([(0.0, 0.0), (0.0, 0.0)]) == 0.0
    assert _settled_coupling([(0.06, 0.1)]) == 0.0  # a world-like drift read a tenth: SLAM-like


def test_the_deskewed_tilt_is_the_patch_average_not_the_instant_sway():
    """A wall swept while walking along it at 0.4 m/s (time slope 2.5 s/m) with a sway of 5 cm at
    2 Hz along the walk (0.63 m/s), under a map that turns each point by 7 mrad about the sensor
    where it was (GNSS/INS-like). The plane a fit finds in the moved points tilts by the walk's mean
    velocity; the deskewed plane must match it. The map's rate at one instant (a 1 cm step) would
    carry the sway into the tilt: 7 mrad x 0.51 m/s x 2.5 s/m, 9 mrad at the patch's mean time."""
    from kinreg.estimate.drift import _deskewed
    from kinreg.geometry import rotvec_to_quat
    from kinreg.types import Plane

    R = Pose(rotvec_to_quat(np.array([0.0, 0.0, 7e-3])), np.zeros(3)).rotation_matrix
    tau_c = 0.3

    def sensor(tau):
        tau = np.asarray(tau, dtype=float)
        return np.stack([0.4 * tau + 0.05 * np.sin(2 * np.pi * 2.0 * tau), 0 * tau, 0 * tau], axis=-1)

    def mapped(x, tau, where=None):
        p = sensor(tau) if where is None else where
        return (np.asarray(x) - p) @ R.T + p

    # The wall y = 3 over x in [-2, 2] (seen at tau = x / 0.4: slope 2.5 s/m along x), z in [0, 2].
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-2, 2, 20000), np.full(20000, 3.0), rng.uniform(0, 2, 20000)])
    moved = mapped(pts, pts[:, 0] / 0.4)
    c = moved.mean(axis=0)
    normal = np.linalg.svd(moved - c, full_matrices=False)[2][-1]
    normal *= np.sign(normal[1])
    # The patch about x = 0.12 m (its mean time tau_c), as kinreg's plane carries it.
    wall = Plane(0, 0, np.array([0.0, 1.0, 0.0]), 3.0, np.array([0.4 * tau_c, 3.0, 1.0]),
                 np.array([[1.0, 0, 0], [0, 0, 1.0]]), np.eye(3) * 1e-8, np.zeros((0, 3)), 8.0, 20000, 0.0,
                 t_offset_s=tau_c, t_slope_s_per_m=(2.5, 0.0))
    def tilt(plane):
        return float(np.arccos(min(1.0, abs(_deskewed(plane, mapped).normal @ normal))))

    assert tilt(wall) < 2e-4
    from dataclasses import replace as replaced
    assert tilt(replaced(wall, area_m2=0.0)) > 2e-3  # the instant's rate (1 cm apart): the sway in it


def test_a_wall_seen_from_a_walk_that_stops_turns_about_where_the_sensor_was():
    """GNSS/INS-like drift: the attitude error (7 mrad of heading) turns each point about the sensor
    where it was. The sensor walks along a wall y = 3 at 0.6 m/s for the first half of the window,
    then stands: the wall's points were seen 0.45 m behind the sensor's position at their mean time,
    on average, so a turn about that position misplaces the wall by 3 mm. Deskewed about where the
    sensor was while it saw them (the plane's sensor moments, from the track), the wall is where it
    is to 0.05 mm; about the mean time's position it is not."""
    from kinreg.estimate.drift import _deskewed, plane_time_offsets
    from kinreg.geometry import rotvec_to_quat
    from kinreg.types import Plane

    R = Pose(rotvec_to_quat(np.array([0.0, 0.0, 7e-3])), np.zeros(3)).rotation_matrix

    def sensor(tau):
        tau = np.asarray(tau, dtype=float)
        return np.stack([0.6 * np.minimum(tau, 0.0), 0 * tau, 0 * tau], axis=-1)

    def turned(x, tau, R):
        p = sensor(tau)
        return (np.asarray(x) - p) @ R.T + p

    rng = np.random.default_rng(3)
    tau = rng.uniform(-3.0, 3.0, 40000)
    truth = np.column_stack([sensor(tau)[:, 0] + rng.uniform(-1.0, 1.0, len(tau)), np.full(len(tau), 3.0),
                             rng.uniform(0.0, 2.0, len(tau))])
    seen = turned(truth, tau, R.T)  # the drift: the heading error turns each point about the sensor
    c = seen.mean(axis=0)
    normal = np.linalg.svd(seen - c, full_matrices=False)[2][-1]
    normal *= np.sign(normal[1])
    u = np.array([1.0, 0.0, 0.0]) - normal[0] * normal
    u /= np.linalg.norm(u)
    basis = np.array([u, np.cross(normal, u)])
    st = (seen - c) @ basis.T
    corners = [(a, b) for a in (st[:, 0].min() - 0.01, st[:, 0].max() + 0.01)
               for b in (st[:, 1].min() - 0.01, st[:, 1].max() + 0.01)]
    wall = Plane(0, 0, normal, float(normal @ c), c, basis, np.eye(3) * 1e-8, c + np.array(corners) @ basis,
                 0.0, len(tau), 0.0)
    track_t = np.linspace(-3.5, 3.5, 701)
    times = plane_time_offsets(seen, tau, 0.0, [wall], 0.05, (track_t, sensor(track_t)))
    (wall,) = times.applied([wall])
    assert wall.sensor_xyz is not None
    assert wall.sensor_xyz[0] == pytest.approx(-0.45, abs=0.02)
    assert float(np.linalg.norm(sensor(wall.t_offset_s))) < 0.02  # the mean time's position: not there

    def mapped(x, t, where=None):  # the correction: back about the sensor
        p = sensor(t) if where is None else where
        return (np.asarray(x) - p) @ R.T + p

    def offset_error(plane):
        moved = _deskewed(plane, mapped)
        return abs(float(moved.normal @ moved.centroid_xyz - 3.0 * moved.normal[1]))

    assert offset_error(wall) < 5e-5
    assert offset_error(replace(wall, sensor_xyz=None, sensor_slope=None)) > 2e-3


@pytest.mark.parametrize(("model", "expected"), [("gnss", 1.0), ("slam", 0.0)])
def test_the_coupling_is_the_one_the_network_fits_best(model, expected):
    """The network's least-squares cost (a-priori weights) at the couplings 0, 1/2 and 1: the
    parabola's vertex names the regime the trajectory drifted in (GNSS/INS-like 1, SLAM-like 0),
    without reading it off an adjustment's attitudes."""
    from kinreg.estimate.drift import coupling_by_fit

    prior = DriftRates(np.full(3, 3e-4), np.full(3, 5e-5), 1e-3, 1e-4)
    stations, links, _ = _coupling_case(model, 0.0)
    fixed = np.arange(len(stations)) == 0
    initial = Pose.stack([s.T_obj_scan for s in stations])
    plain = BlockConfig(data_snooping=False, variance_components=False)
    couplings, costs = (0.0, 0.5, 1.0), []
    for kappa in couplings:
        result = adjust_block(initial, block_observations(stations, links, replace(prior, coupling=kappa)), fixed,
                              plain)
        assert not result.failed
        costs.append(result.sigma0**2 * result.redundancy)
    found = coupling_by_fit(couplings, costs)
    assert found == pytest.approx(expected, abs=0.2), (costs, found)


def test_the_coupling_by_fit_is_the_parabola_s_vertex_within_the_bounds():
    from kinreg.estimate.drift import coupling_by_fit

    x = (0.0, 0.5, 1.0)
    assert coupling_by_fit(x, [(k - 0.8) ** 2 + 3.0 for k in x]) == pytest.approx(0.8)
    assert coupling_by_fit(x, [(k - 1.7) ** 2 for k in x]) == 1.0  # the vertex beyond 1
    assert coupling_by_fit(x, [162.0, 336.0, 413.0]) == 0.0  # opens downwards: the cheaper end
    assert coupling_by_fit(x, [np.inf, 5.0, 4.0]) == 1.0  # a failed adjustment: the cheapest tried


def test_a_coupling_fits_better_only_where_the_cost_falls_significantly():
    """The coupling as one more unknown: an F-test of the fall in cost against the cost's own sigma0.
    A network without redundancy (a cost of ~0 at every coupling) tells nothing."""
    from kinreg.estimate.drift import fits_better

    assert fits_better(642.0, 810.0, 500.0, 0.001)  # the sample's run that settled on 0.32
    assert not fits_better(642.0, 650.0, 500.0, 0.001)  # 8 of 1.3 per unit: within the noise
    assert not fits_better(6.8e-11, 3.0e-10, 0.0, 0.001)
    assert fits_better(80.0, 95.0, 78.0, 0.001) and not fits_better(80.0, 90.0, 78.0, 0.001)  # F(1, 78) 11.7
