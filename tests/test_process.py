"""`kinreg process` end to end on a small simulated run: every output, and the truth comes back."""

import csv
import json

import laspy
import numpy as np
import pytest
from kinreg_cli.main import main

from kinreg.io.e57 import list_e57_scans
from kinreg.io.trajectory import read_trajectory
from kinreg.report.json import rigid_fit
from kinreg.report.tables import STATIONS_HEADER
from kinreg.simulation.files import write_run
from kinreg.simulation.run import SimulationConfig, simulate_run


@pytest.fixture(scope="module")
def processed(tmp_path_factory):
    root = tmp_path_factory.mktemp("process")
    run = simulate_run(SimulationConfig(seed=3, duration_s=60.0))
    write_run(run, root / "data")
    with pytest.raises(SystemExit) as info:
        main(["process", "-t", str(root / "data" / "run_trajectory.txt"), "-c", str(root / "data" / "run_cloud.laz"),
              "-o", str(root / "out")])
    assert info.value.code == 0
    return root


def test_all_outputs_are_written(processed):
    names = sorted(p.name for p in (processed / "out").iterdir())
    assert names == sorted(["config.toml", "control_points.csv", "corrected.laz", "links.csv", "planes.csv",
                            "report.html", "report.json", "sequence.e57", "stations.csv", "trajectory_corrected.txt",
                            ".kinreg-cache",  # the stage cache, for --resume
                            "figures"])  # the report's images of the cloud


def test_stations_csv_contract(processed):
    with open(processed / "out" / "stations.csv") as f:
        reader = csv.reader(f)
        header = next(reader)
        rows = list(reader)
    assert header == STATIONS_HEADER
    assert len(rows) == 10  # 60 s in 6 s windows
    assert rows[0][header.index("s3d_mm")] == "0.000"  # the datum station


def test_adjusted_stations_are_closer_to_the_truth(processed):
    with open(processed / "out" / "stations.csv") as f:
        rows = list(csv.DictReader(f))
    t = np.array([float(r["t"]) for r in rows])
    adjusted = np.array([[float(r[k]) for k in "xyz"] for r in rows])
    truth = read_trajectory(processed / "data" / "truth_trajectory.txt").pose_at(t).t_xyz
    R, tt = rigid_fit(adjusted, truth)
    err = np.linalg.norm(adjusted @ R.T + tt - truth, axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.003


def test_corrected_cloud_keeps_points_order_and_attributes(processed):
    src = laspy.read(processed / "data" / "run_cloud.laz")
    out = laspy.read(processed / "out" / "corrected.laz")
    assert len(src.points) == len(out.points)
    assert out.header.point_format.id == src.header.point_format.id
    np.testing.assert_array_equal(out.gps_time, src.gps_time)
    np.testing.assert_array_equal(out.intensity, src.intensity)
    shift = np.linalg.norm(np.column_stack([out.x - src.x, out.y - src.y, out.z - src.z]), axis=1)
    assert shift.max() < 0.05  # a drift correction, not a different cloud


def test_corrected_trajectory_same_rows(processed):
    a = read_trajectory(processed / "data" / "run_trajectory.txt")
    b = read_trajectory(processed / "out" / "trajectory_corrected.txt")
    np.testing.assert_allclose(a.stamps_s, b.stamps_s, atol=1e-6)


def test_sequence_has_the_adjusted_poses(processed):
    scans = list_e57_scans(processed / "out" / "sequence.e57")
    with open(processed / "out" / "stations.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(scans) == len(rows)
    for scan, row in zip(scans, rows, strict=True):
        np.testing.assert_allclose(scan.T_obj_scan.t_xyz, [float(row[k]) for k in "xyz"], atol=1e-6)


def test_report_json(processed):
    report = json.loads((processed / "out" / "report.json").read_text())
    assert report["schema_version"] == 1
    assert report["stations"]["n"] == 10
    assert report["adjustment"]["sigma0"] > 0
    assert set(report["timings_s"]) >= {"slice", "planes", "link", "block"}


def test_the_block_adjusts_the_planes_as_nodes(processed):
    """With ``[block] plane_nodes`` (the default): the report carries the planes' two variance
    components, and each link in links.csv the block test of its worst plane."""
    report = json.loads((processed / "out" / "report.json").read_text())
    assert {"plane", "plane offset"} <= set(report["adjustment"]["variance_components"])
    with open(processed / "out" / "links.csv") as f:
        links = [r for r in csv.DictReader(f) if r["status"] == "ok"]
    assert links and all(np.isfinite(float(r["block_normalised"])) for r in links)


def test_existing_results_are_not_overwritten(processed, capsys):
    with pytest.raises(SystemExit) as info:
        main(["process", "-t", str(processed / "data" / "run_trajectory.txt"),
              "-c", str(processed / "data" / "run_cloud.laz"), "-o", str(processed / "out")])
    assert info.value.code == 1
    assert "already holds kinreg results; use --overwrite" in capsys.readouterr().err


def run_process(root, name, *extra):
    with pytest.raises(SystemExit) as info:
        main(["process", "-t", str(root / "data" / "run_trajectory.txt"), "-c", str(root / "data" / "run_cloud.laz"),
              "-o", str(root / name), *map(str, extra)])
    return info.value.code


def absolute_errors_mm(root, name):
    with open(root / name / "stations.csv") as f:
        rows = [r for r in csv.DictReader(f) if r["t"]]
    t = np.array([float(r["t"]) for r in rows])
    adjusted = np.array([[float(r[k]) for k in "xyz"] for r in rows])
    truth = read_trajectory(root / "data" / "truth_trajectory.txt").pose_at(t).t_xyz
    return np.linalg.norm(adjusted - truth, axis=1) * 1000.0


def test_static_scans_fixed_as_datum(processed):
    assert run_process(processed, "static", "--static", processed / "data" / "static.e57") == 0
    with open(processed / "static" / "stations.csv") as f:
        rows = list(csv.DictReader(f))
    static = [r for r in rows if not r["t"]]
    assert len(static) == 3 and all(r["s3d_mm"] == "0.000" for r in static)
    truth = json.loads((processed / "data" / "static_truth.json").read_text())
    for row, scan in zip(static, truth["scans"], strict=True):
        np.testing.assert_allclose([float(row[k]) for k in "xyz"], scan["t_xyz"], atol=1e-6)  # held fixed
    assert np.sqrt(np.mean(absolute_errors_mm(processed, "static") ** 2)) < 3.0
    report = json.loads((processed / "static" / "report.json").read_text())
    assert report["adjustment"]["datum"] == "static scans fixed"


def test_reference_planes_as_datum_and_as_built(processed):
    assert run_process(processed, "reference", "--reference", processed / "data" / "reference.toml") == 0
    report = json.loads((processed / "reference" / "report.json").read_text())
    assert report["adjustment"]["datum"].startswith("reference planes")
    planes = {p["name"]: p for p in report["reference"]["planes"]}
    assert all(p["n_ties"] > 0 for p in planes.values())
    # the simulated building is exactly as planned: tie corrections are at the millimetre level
    assert all(abs(p["offset_mean_mm"]) < 2.0 for p in planes.values())
    assert np.sqrt(np.mean(absolute_errors_mm(processed, "reference") ** 2)) < 5.0


def test_reference_file_with_errors_is_one_line(processed, capsys):
    bad = processed / "bad_reference.toml"
    bad.write_text('plane_construction_accuracy_m = 0.05\n[[plane]]\nname = "w"\naxis = "q"\n'
                   'offset_m = 0\nnormal_sign = 1\n')
    assert run_process(processed, "bad_reference", "--reference", bad) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"kinreg: error: {bad}") and "axis" in err and len(err.splitlines()) == 1
    assert not (processed / "bad_reference" / "stations.csv").exists()
