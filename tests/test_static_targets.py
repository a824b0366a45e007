"""Targets in static scans as control and check points (issue 15): the reader's target rows, their
static scan, the observation of the static station's pose, its datum and screening, bad files
through the command line, and one simulated run."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from clirunner import run_cli
from conftest import write_synthetic_run

from kinreg.config import ControlConfig, KinregConfig, StaticConfig
from kinreg.errors import InputError
from kinreg.estimate.control import assign_points, control_observations, target_ties
from kinreg.estimate.datum import adjust_network, build_network, screen_control_points
from kinreg.estimate.drift import DriftRates
from kinreg.geometry import Pose, rotvec_to_quat
from kinreg.io.control import parse_control_points
from kinreg.progress import NullProgress
from kinreg.types import ScanKind, Station

MIXED = ("name,x,y,z,sigma_mm,station,sx,sy,sz\n"
         "CP01,1.0,2.0,3.0,3,,,,\n"
         "T1,10.0,20.0,1.5,2,scan_a,4.0,-1.0,0.5\n"
         "T2,11.0,21.0,2.5,2,1,3.0,2.0,1.0\n")


def test_reader_reads_target_rows_beside_stand_still_rows():
    points = parse_control_points(MIXED, "cp.csv")
    assert points.names == ("CP01", "T1", "T2")
    assert not points.points[0].is_target and points.points[0].station == ""
    assert [t.name for t in points.targets] == ["T1", "T2"]
    t1 = points.targets[0]
    assert t1.station == "scan_a" and np.allclose(t1.scan_xyz, [4.0, -1.0, 0.5]) and t1.sigma_m == pytest.approx(0.002)
    assert t1.line == 3


def test_targets_name_their_static_scan_by_name_or_position():
    points = parse_control_points(MIXED.replace("CP01,1.0,2.0,3.0,3,,,,\n", ""), "cp.csv")
    assignment = assign_points(points, [], ControlConfig(), static_scans=["scan_a", "scan_b"])
    assert assignment.names == () and assignment.all_names == ("T1", "T2")
    assert [(t.scan, t.scan_name) for t in assignment.targets] == [(0, "scan_a"), (1, "scan_b")]
    with pytest.raises(InputError, match="line 2: control target T1: no static scan 'scan_a'"):
        assign_points(points, [], ControlConfig(), static_scans=["other", "more"])
    with pytest.raises(InputError, match="line 2: check target T1 names static scan 'scan_a', but no static scans"):
        assign_points(points, [], ControlConfig(), "check")


def _static(k: int, T: Pose) -> Station:
    return Station(k, f"static_{k:03d}", ScanKind.STATIC, float("nan"), float("nan"), float("nan"), T, 1000)


def _scene(rng: np.random.Generator, n_targets: int = 5) -> tuple[Pose, Pose, np.ndarray]:
    """A static scan's true pose, its pose in the E57 file (2 cm and 0.1 deg off) and targets on
    walls 3-10 m around it (object frame)."""
    T_true = Pose(rotvec_to_quat(np.array([0.0003, -0.0002, 1.1])), np.array([500012.3, 5400001.4, 101.5]))
    T_file = T_true.compose(Pose(rotvec_to_quat(np.radians([0.05, -0.04, 0.08])), np.array([0.015, -0.012, 0.004])))
    a = np.linspace(0.0, 2.0 * np.pi, n_targets, endpoint=False) + 0.3
    r = rng.uniform(3.0, 10.0, n_targets)
    scan_xyz = np.column_stack([r * np.cos(a), r * np.sin(a), rng.uniform(-1.0, 1.5, n_targets)])
    return T_true, T_file, T_true.apply(scan_xyz)


def _targets_csv(true_xyz: np.ndarray, scan_xyz: np.ndarray, sigma_mm: float) -> str:
    return "name,x,y,z,sigma_mm,station,sx,sy,sz\n" + "".join(
        f"T{k + 1},{p[0]:.5f},{p[1]:.5f},{p[2]:.5f},{sigma_mm},0,{s[0]:.5f},{s[1]:.5f},{s[2]:.5f}\n"
        for k, (p, s) in enumerate(zip(true_xyz, scan_xyz, strict=True)))


def _network(text: str, T_file: Pose, config: KinregConfig):
    assignment = assign_points(parse_control_points(text, "targets.csv"), [], config.control, static_scans=["s"])
    stations = [_static(0, T_file)]
    ties = target_ties(assignment.targets, stations, config.control)
    return build_network(stations, [()], [], None, StaticConfig(), config, ties)


def test_targets_alone_hold_their_static_station_within_its_sigmas():
    """Four targets on one static scan, the scan's pose in its file off by 2 cm and 0.1 deg: the
    targets alone are the datum (the file's pose is only the start, [static] datum = fixed does
    not hold it), the adjusted pose reaches the truth, and error/sigma over 200 draws of the survey
    and scan noise is about 1."""
    config = KinregConfig()
    rates = DriftRates.from_config(config.drift)
    sigma_survey, sigma_scan = 3.0, config.control.target_sigma_mm
    rng = np.random.default_rng(5)
    z = []
    for _ in range(200):
        T_true, T_file, true_xyz = _scene(rng, 4)
        surveyed = true_xyz + 1e-3 * sigma_survey * rng.standard_normal(true_xyz.shape)
        measured = T_true.inverse().apply(true_xyz) + 1e-3 * sigma_scan * rng.standard_normal(true_xyz.shape)
        network = _network(_targets_csv(surveyed, measured, sigma_survey), T_file, config)
        assert not network.datum.fixed.any() and not network.datum.observations
        assert "4 control point(s), 4 of them targets in static scan(s) static_000" in network.datum.description
        result = adjust_network(network, rates, config.block, NullProgress())
        e = result.poses.t_xyz[0] - T_true.t_xyz
        assert np.linalg.norm(e) < 0.01
        z.append(e / np.sqrt(np.diag(result.cov_position[0])))
    ratio = np.sqrt(np.mean(np.square(z), axis=0))
    assert np.all((ratio > 0.8) & (ratio < 1.25)), ratio


def test_a_target_moved_by_5_cm_is_rejected_and_named():
    config = KinregConfig()
    rates = DriftRates.from_config(config.drift)
    rng = np.random.default_rng(11)
    T_true, T_file, true_xyz = _scene(rng, 5)
    surveyed = true_xyz + 0.003 * rng.standard_normal(true_xyz.shape)
    surveyed[2, 0] += 0.05
    measured = T_true.inverse().apply(true_xyz) + 0.002 * rng.standard_normal(true_xyz.shape)
    network = _network(_targets_csv(surveyed, measured, 3.0), T_file, config)
    screened = screen_control_points(network, rates, config.block, NullProgress())
    assert [name for name, _ in screened.datum.rejected_controls] == ["T3"]
    result = adjust_network(screened, rates, config.block, NullProgress())
    assert np.linalg.norm(result.poses.t_xyz[0] - T_true.t_xyz) < 0.01


def test_a_target_is_one_point_observation_of_its_static_station_without_trajectory_terms():
    config = KinregConfig()
    rng = np.random.default_rng(2)
    T_true, T_file, true_xyz = _scene(rng, 3)
    network = _network(_targets_csv(true_xyz, T_true.inverse().apply(true_xyz), 3.0), T_file, config)
    observations = control_observations(network.datum.controls, network.stations, DriftRates.from_config(config.drift))
    expected = 1.0 / (0.003**2 + 0.002**2)
    for o in observations:
        assert (o.i, o.j, o.rank) == (0, -1, 3) and np.allclose(o.info[:3, :3], expected * np.eye(3))


def _static_e57(path: Path, near: np.ndarray) -> None:
    from kinreg.simulation.files import write_static_e57
    from kinreg.types import Scan

    rng = np.random.default_rng(3)
    points = rng.normal(0.0, 4.0, (2000, 3))
    write_static_e57(path, [Scan(0, "tls_a", ScanKind.STATIC, Pose(np.array([1.0, 0, 0, 0]), near), points)])


@pytest.mark.parametrize(("text", "static", "reason"), [
    ("name,x,y,z,sigma_mm,station,sx,sy,sz\nT1,1,2,3,3,tls_b,1,2,3\n", True, "line 2: {what} target T1: no static "
                                                                            "scan 'tls_b'"),
    ("name,x,y,z,sigma_mm,station,sx,sy,sz\nT1,1,2,3,3,tls_a,1,2,3\n", False, "names static scan 'tls_a', but no "
                                                                             "static scans are given"),
    ("name,x,y,z,sigma_mm,station,sx,sy,sz\nT1,1,2,3,3,tls_a,1,,3\n", True, "line 2: target T1 in static scan tls_a: "
                                                                           "sy missing"),
    ("name,x,y,z,sigma_mm,station,sx,sy,sz\nT1,1,2,3,3,tls_a,1,2,nan\n", True, "sz is not a finite number"),
    ("name,x,y,z,sigma_mm,station,sx\nT1,1,2,3,3,tls_a,1\n", True, "without sy, sz"),
])
def test_bad_target_rows_stop_with_one_line(tmp_path, capsys, text, static, reason):
    run = write_synthetic_run(tmp_path / "run", n_points=5000, duration_s=10.0)
    bad = tmp_path / "bad.csv"
    bad.write_text(text)
    e57 = tmp_path / "static.e57"
    _static_e57(e57, run.trajectory.poses.t_xyz[0])
    out = tmp_path / "out"
    for option, what in (("--control", "control"), ("--check", "check")):
        args = ["process", "-t", run.trajectory_path, "-c", run.cloud_path, "-o", out, option, bad, "--workers", "1"]
        code, _, err = run_cli(args + (["--static", e57] if static else []), capsys)
        lines = [line for line in err.splitlines() if line.startswith("kinreg: error")]
        assert code == 1 and len(lines) == 1 and str(bad) in lines[0], err
        assert reason.format(what=what) in lines[0], lines[0]
        assert "Traceback" not in err
        assert not (out / "report.json").exists() and not (out / "stations.csv").exists()


@pytest.mark.slow
def test_simulated_run_with_static_targets_as_the_only_datum(tmp_path):
    """The committed sample's run with its three static scans off by 2 cm and 0.1 deg in their E57
    file and four targets on each (survey 3 mm, scan 2 mm), one moved by 5 cm, and a check target
    on another: the targets are the datum, the wrong one is rejected and named, the stations land
    on the truth within a few mm, and the report marks the targets."""
    from kinreg.io.trajectory import read_trajectory
    from kinreg.run.pipeline import ProcessInputs, process
    from kinreg.simulation.files import static_targets_csv, write_static_e57
    from kinreg.simulation.run import config_from_dict, simulate_run

    sample = Path(__file__).resolve().parents[1] / "sample_data"
    run = simulate_run(config_from_dict(json.loads((sample / "run_meta.json").read_text())["config"]))
    static = tmp_path / "static.e57"
    write_static_e57(static, run.static_scans_misregistered(0.02, 0.1))
    names = [t.name for t in run.static_targets()]
    control, check = tmp_path / "targets.csv", tmp_path / "check.csv"
    control.write_text(static_targets_csv(run, names=[n for n in names if n != "S02T4"], moved={"S01T2": (0.05, 0, 0)}))
    check.write_text(static_targets_csv(run, noise=False, names=["S02T4"]))
    out = tmp_path / "out"
    process(ProcessInputs(sample / "run_trajectory.txt", sample / "run_cloud.laz", static=static, control=control,
                          check=check), out, KinregConfig())
    report = json.loads((out / "report.json").read_text())
    assert report["control"]["rejected"] == ["S01T2"]
    assert "targets in static scan(s)" in report["adjustment"]["datum"]
    assert "static scans fixed" not in report["adjustment"]["datum"]
    assert {r["kind"] for r in report["control"]["rows"]} == {"static target"}
    assert report["check"]["rows"][0]["kind"] == "static target"
    assert report["check"]["summary"]["d3d_mm"]["rms"] < 10.0
    assert report["check"]["summary_input"]["d3d_mm"]["rms"] > 10.0  # the E57 pose was 2 cm off
    assert "static target" in (out / "control_points.csv").read_text()
    rows = np.genfromtxt(out / "stations.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    quasi = np.array([str(t) != "" and np.isfinite(float(t or "nan")) for t in rows["t"]])
    t = rows["t"][quasi].astype(float)
    truth = read_trajectory(sample / "truth_trajectory.txt").pose_at(t).t_xyz
    err = np.column_stack([rows["x"][quasi], rows["y"][quasi], rows["z"][quasi]]) - truth
    assert np.sqrt(np.mean(np.sum(err**2, axis=1))) < 0.01


def test_report_tables_mark_static_targets():
    from kinreg.report.control import CONTROL_POINTS_HEADER, control_html, format_control_points_csv

    row = {"name": "T1", "role": "control", "kind": "static target", "scan": "static_00", "t": float("nan"),
           "x": 1.0, "y": 2.0, "z": 3.0, "sigma_mm": 3.0, "dx_mm": 1.0, "dy_mm": 0.0, "dz_mm": 0.0,
           "horizontal_mm": 1.0, "vertical_mm": 0.0, "d3d_mm": 1.0, "normalised": 0.3, "decision": "accepted",
           "input_d3d_mm": 20.0}
    report = {"control": {"n": 1, "rows": [row], "rejected": [], "left_out": []}}
    lines = format_control_points_csv(report).splitlines()
    assert CONTROL_POINTS_HEADER[16:18] == ("kind", "scan")
    assert lines[1].startswith("T1,control,,") and ",static target,static_00," in lines[1]
    html = control_html(report)
    assert "static target static_00" in html and "the target on its adjusted static scan" in html


def _link(i: int, j: int, info_diag) -> object:
    from kinreg.types import Link, LinkStatus

    eye = Pose.identity()
    return Link(i, j, LinkStatus.OK, eye, np.eye(6), eye, eye, np.diag(info_diag), int(np.count_nonzero(info_diag)),
                np.ones(6), 2, 1.0, 10, True, (), (), 1.0, 6.0)


def test_a_static_scan_whose_links_leave_a_direction_free_is_named():
    """A static scan (index 2) whose links see no plane across the x axis (a corridor): the
    translation along x is named; with a link that sees one, nothing is."""
    from kinreg.estimate.datum import free_static_directions

    stations = [Station(k, f"qs_{k}", ScanKind.QUASI_STATIC, float(k), k - 1.0, k + 1.0, Pose.identity(), 100)
                for k in range(2)] + [_static(2, Pose.identity())]
    corridor = [0.0, 1e6, 1e6, 1e9, 1e9, 1e9]
    assert free_static_directions(stations, [_link(0, 2, corridor), _link(2, 1, corridor)], [2]) == [
        "translation along x"]
    across = [1e6, 0.0, 1e6, 1e9, 1e9, 1e9]
    assert free_static_directions(stations, [_link(0, 2, corridor), _link(1, 2, across)], [2]) == []
    assert free_static_directions(stations, [_link(0, 1, across)], [2]) == [
        "translation along x", "translation along y", "translation along z", "rotation about x", "rotation about y",
        "rotation about z"]


def test_with_targets_no_static_scan_is_held_at_its_e57_pose():
    """Two static scans, targets on the first only, [static] datum = fixed: neither is fixed (the
    targets are the datum; the second joins through its link, its E57 pose observed with the
    static prior's 0.2 m), and the datum says so; with "observed" the second is observed with
    [static] sigma_mm. One target alone leaves the rotations to the first station."""
    import dataclasses

    from kinreg.config import StaticDatum
    from kinreg.types import ObservationKind

    rng = np.random.default_rng(4)
    T_true, T_file, true_xyz = _scene(rng, 4)
    stations = [_static(0, T_file), _static(1, T_file.compose(Pose(np.array([1.0, 0, 0, 0]), np.array([5.0, 0, 0]))))]
    text = _targets_csv(true_xyz, T_true.inverse().apply(true_xyz), 3.0)
    assignment = assign_points(parse_control_points(text, "t.csv"), [], ControlConfig(), static_scans=["a", "b"])
    ties = target_ties(assignment.targets, stations, ControlConfig())
    link = _link(0, 1, [1e6] * 3 + [1e9] * 3)
    config = KinregConfig()
    network = build_network(stations, [(), ()], [link], None, StaticConfig(), config, ties)
    assert not network.datum.fixed.any()
    (prior,) = network.datum.observations  # the E57 pose, weakly: for what the planes leave free
    assert (prior.kind, prior.i) == (ObservationKind.STATION, 1) and prior.info[0, 0] == pytest.approx(1 / 0.2**2)
    assert "static scans without targets not fixed" in network.datum.description
    observed = build_network(stations, [(), ()], [link], None, StaticConfig(datum=StaticDatum.OBSERVED), config, ties)
    (held,) = observed.datum.observations
    assert (held.kind, held.i) == (ObservationKind.STATION, 1) and held.info[0, 0] == pytest.approx(1 / 0.002**2)
    one = build_network(stations, [(), ()], [link], None, StaticConfig(), config, ties[:1])
    assert [(o.kind, o.i, o.rank) for o in one.datum.observations] == [(ObservationKind.STATION, 1, 6),
                                                                        (ObservationKind.STATION, 0, 3)]
    assert "fixing translations; the first station's rotation about every axis" in one.datum.description
    from kinreg.errors import ConfigError

    with pytest.raises(ConfigError, match="target_sigma_mm"):
        dataclasses.replace(config.control, target_sigma_mm=-1.0)
