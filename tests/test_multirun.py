"""Several runs in one project: two simulated walks through the same building, processed together.

Run 2 is delivered 3 cm off run 1's frame (its SLAM started there: ``origin_xyz``), an hour
later. Its truth in the common frame is its truth file less that offset. Linked through identical
planes, both runs come out in one frame: a run-1 station and a nearby run-2 station are as far
apart as in truth, to the millimetre.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import shutil
from pathlib import Path

import laspy
import numpy as np
import pytest
from conftest import SAMPLE_DATA
from kinreg_cli.main import main

from kinreg.config import DriftConfig, KinregConfig, MatchingConfig
from kinreg.estimate.drift import DriftRates
from kinreg.estimate.network import block_observations, station_pairs
from kinreg.geometry import Pose
from kinreg.io.e57 import list_e57_scans
from kinreg.io.trajectory import read_trajectory
from kinreg.report.json import rigid_fit
from kinreg.run.pipeline import OUTPUT_FILES, ProcessInputs, process
from kinreg.simulation.files import write_run
from kinreg.simulation.run import config_from_dict, simulate_run
from kinreg.types import ObservationKind, ScanKind, Station

# (seed, start after run 1 [s], offset of the run's frame [m])
RUNS = ((11, 0.0, (0.0, 0.0, 0.0)), (12, 3600.0, (0.03, -0.02, 0.0)))
N_SCANS = 17  # per run: 100 s in 6 s windows


def cli(*args: object) -> int:
    with pytest.raises(SystemExit) as info:
        main([str(a) for a in args])
    return int(info.value.code)


@pytest.fixture(scope="module")
def project(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two 100 s runs of the sample configuration (different walks and drifts), processed together."""
    root = tmp_path_factory.mktemp("multirun")
    sample = config_from_dict(json.loads((SAMPLE_DATA / "run_meta.json").read_text())["config"])
    for k, (seed, start_s, origin) in enumerate(RUNS, 1):
        config = dataclasses.replace(sample, seed=seed, duration_s=100.0, t0_s=sample.t0_s + start_s,
                                     origin_xyz=origin)
        write_run(simulate_run(config), root / f"run{k}")
    code = cli("process", *run_args(root, 1, 2), "-o", root / "out", "--workers", 1)
    assert code == 0
    return root


def run_args(root: Path, *runs: int) -> list[object]:
    args: list[object] = []
    for k in runs:
        args += ["-t", root / f"run{k}" / "run_trajectory.txt", "-c", root / f"run{k}" / "run_cloud.laz"]
    return args


def stations(folder: Path) -> list[dict[str, str]]:
    with open(folder / "stations.csv") as f:
        return list(csv.DictReader(f))


def links(folder: Path) -> list[dict[str, str]]:
    with open(folder / "links.csv") as f:
        return list(csv.DictReader(f))


def positions(root: Path, rows: list[dict[str, str]], source: str) -> np.ndarray:
    """Station positions at the stations' times in the common frame: of ``source`` ("truth" or
    "run": the delivered trajectory) of each station's run."""
    out = np.zeros((len(rows), 3))
    for k, (_, _, origin) in enumerate(RUNS, 1):
        own = np.array([r["station"].startswith(f"r{k}_") for r in rows])
        t = np.array([float(r["t"]) for r, o in zip(rows, own, strict=True) if o])
        trajectory = read_trajectory(root / f"run{k}" / f"{source}_trajectory.txt")
        out[own] = trajectory.pose_at(t).t_xyz - (np.asarray(origin) if source == "truth" else 0.0)
    return out


def cross_run_errors_mm(root: Path, estimated: np.ndarray, rows: list[dict[str, str]]) -> np.ndarray:
    """For each run-2 station and its nearest run-1 station: the error of their relative position."""
    truth = positions(root, rows, "truth")
    first = np.flatnonzero([r["station"].startswith("r1_") for r in rows])
    errors = []
    for j in np.flatnonzero([r["station"].startswith("r2_") for r in rows]):
        i = first[np.argmin(np.linalg.norm(truth[first] - truth[j], axis=1))]
        errors.append(np.linalg.norm((estimated[j] - estimated[i]) - (truth[j] - truth[i])))
    return np.array(errors) * 1000.0


def test_stations_are_named_and_numbered_by_run(project: Path) -> None:
    rows = stations(project / "out")
    assert [r["station"] for r in rows] == [f"r{k}_qs_{n:05d}" for k in (1, 2) for n in range(N_SCANS)]
    report = json.loads((project / "out" / "report.json").read_text())
    assert report["schema_version"] == 1 and report["adjustment"]["datum"] == "first station"
    assert report["inputs"]["trajectory"] is None and [r["station_prefix"] for r in report["inputs"]["runs"]] == [
        "r1_", "r2_"]
    assert [r["cloud"] for r in report["inputs"]["runs"]] == [str(project / f"run{k}" / "run_cloud.laz")
                                                              for k in (1, 2)]
    assert report["inputs"]["n_points"] == sum(r["n_points"] for r in report["inputs"]["runs"])
    assert report["slicing"]["n_scans"] == 2 * N_SCANS
    # gaps before vs after: one rigid fit per run (the runs' frames differ by the 36 mm)
    assert report["before_after"]["type"] == "rigid per run" and len(report["before_after"]["runs"]) == 2
    assert len(report["before_after"]["gap_per_station_mm"]) == 2 * N_SCANS
    assert report["before_after"]["gaps_mm"]["max"] < 10.0


def test_every_station_of_the_second_run_is_linked_to_the_first(project: Path) -> None:
    rows = stations(project / "out")
    run = np.array([int(r["station"][1]) for r in rows])
    ok = [link for link in links(project / "out") if link["status"] == "ok"]
    across = [link for link in ok if run[int(link["scan_i"])] != run[int(link["scan_j"])]]
    assert all(link["dt_s"] == "" for link in across)  # no trajectory between two runs
    linked = {int(link[k]) for link in across for k in ("scan_i", "scan_j")}
    assert set(np.flatnonzero(run == 2)) <= linked
    assert len(across) >= 2 * N_SCANS
    # the trajectory ties consecutive stations of one run only: no link from r1's last to r2's first
    assert all(run[int(link["scan_j"])] == 2 for link in across)


def test_both_runs_come_out_in_one_frame(project: Path) -> None:
    rows = stations(project / "out")
    adjusted = np.array([[float(r[k]) for k in "xyz"] for r in rows])
    truth = positions(project, rows, "truth")
    R, t = rigid_fit(adjusted, truth)  # one rigid fit over the stations of both runs
    errors = np.linalg.norm(adjusted @ R.T + t - truth, axis=1) * 1000.0
    assert np.sqrt(np.mean(errors**2)) < 2.0 and errors.max() < 4.0
    before = cross_run_errors_mm(project, positions(project, rows, "run"), rows)
    after = cross_run_errors_mm(project, adjusted, rows)
    assert np.median(before) > 20.0  # the 36 mm between the runs' frames, give or take the drift
    assert np.sqrt(np.mean(after**2)) < 2.0 and after.max() < 3.0


def test_corrected_cloud_and_trajectory_per_run(project: Path) -> None:
    out = project / "out"
    assert sorted(p.name for p in out.iterdir()) == sorted([
        ".kinreg-cache", "config.toml", "control_points.csv", "corrected_r1.laz", "corrected_r2.laz", "links.csv",
        "planes.csv", "report.html", "report.json", "sequence.e57", "stations.csv", "trajectory_corrected_r1.txt",
        "trajectory_corrected_r2.txt", "figures"])
    for k in (1, 2):
        source = laspy.read(project / f"run{k}" / "run_cloud.laz")
        corrected = laspy.read(out / f"corrected_r{k}.laz")
        assert len(corrected.points) == len(source.points)
        np.testing.assert_array_equal(corrected.gps_time, source.gps_time)
        shift = np.linalg.norm(np.column_stack([corrected.x - source.x, corrected.y - source.y,
                                                corrected.z - source.z]), axis=1)
        assert shift.max() < 0.1  # run 2 moves by its 36 mm frame offset plus its drift
        rows = read_trajectory(project / f"run{k}" / "run_trajectory.txt")
        np.testing.assert_allclose(read_trajectory(out / f"trajectory_corrected_r{k}.txt").stamps_s, rows.stamps_s,
                                   atol=1e-6)
    scans = list_e57_scans(out / "sequence.e57")
    assert [s.name for s in scans] == [r["station"] for r in stations(out)]


def test_mismatched_trajectories_and_clouds_is_one_line(project: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = run_args(project, 1, 2)[:-2]  # two trajectories, one cloud
    assert cli("process", *args, "-o", project / "mismatch") == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("kinreg: error: 2 trajectories (--trajectory) but 1 clouds (--cloud)")
    assert len(err.splitlines()) == 1
    assert not (project / "mismatch").exists()


def test_resume_reuses_each_run_and_one_run_replaces_the_per_run_outputs(project: Path) -> None:
    out = project / "resumed"
    shutil.copytree(project / "out", out)
    inputs = ProcessInputs.from_runs([project / f"run{k}" / "run_trajectory.txt" for k in (1, 2)],
                                     [project / f"run{k}" / "run_cloud.laz" for k in (1, 2)])
    expected = {name: (project / "out" / name).read_bytes() for name in (
        "stations.csv", "links.csv", "sequence.e57", "corrected_r1.laz", "corrected_r2.laz",
        "trajectory_corrected_r2.txt")}
    summary = process(inputs, out, KinregConfig(), resume=True)
    assert summary.n_runs == 2
    assert summary.stage_cache == {
        "slice": {"reused": 2, "computed": 0},
        "planes": {"reused": 2 * N_SCANS, "computed": 0},
        "link": {"reused": 1, "computed": 0},
        "block": {"reused": 0, "computed": 1},
        "corrected cloud": {"reused": 2, "computed": 0},
        "sequence E57": {"reused": 1, "computed": 0},
    }
    (out / "sequence.e57").unlink()  # the points of both runs are needed again: each run is sliced again
    summary = process(inputs, out, KinregConfig(), resume=True)
    assert summary.stage_cache["slice"] == {"reused": 2, "computed": 2}
    assert {name: (out / name).read_bytes() for name in expected} == expected
    # one run in the same folder: the per-run outputs of the two-run project go
    single = ProcessInputs(project / "run1" / "run_trajectory.txt", project / "run1" / "run_cloud.laz")
    process(single, out, KinregConfig(), overwrite=True)
    assert not list(out.glob("*_r[12].*"))
    assert {p.name for p in out.iterdir()} == {*OUTPUT_FILES, ".kinreg-cache", "figures"}
    assert stations(out)[0]["station"] == "qs_00000"


def test_the_trajectory_ties_consecutive_stations_of_one_run_only() -> None:
    """Station pairs and trajectory links of two runs side by side on one line, 1 m apart."""
    def station(k: int, run: int) -> Station:
        pose = Pose(np.array([1.0, 0, 0, 0]), np.array([float(k % 4), 0.0, 0.0]))
        return Station(k, f"s{k}", ScanKind.QUASI_STATIC, 100.0 * k, 100.0 * k - 3, 100.0 * k + 3, pose, 1000,
                       run=run)

    network = [station(k, 0) for k in range(4)] + [station(k, 1) for k in range(4, 8)]
    pairs = station_pairs(network, MatchingConfig(neighbour_depth=1, radius_m=0.5))
    # sequence neighbours within each run, and across runs only by proximity (same place)
    assert pairs == [(0, 1), (0, 4), (1, 2), (1, 5), (2, 3), (2, 6), (3, 7), (4, 5), (5, 6), (6, 7)]
    observations = block_observations(network, [], DriftRates.from_config(DriftConfig()))
    assert [(o.i, o.j) for o in observations if o.kind is ObservationKind.TRAJECTORY] == [
        (0, 1), (1, 2), (2, 3), (4, 5), (5, 6), (6, 7)]
