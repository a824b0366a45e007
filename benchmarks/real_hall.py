"""The real hall: kinreg on real scans with drift added, judged by how crisp the corrected cloud is.

The data is a public indoor hall (repository ``hku-mars/BALM``, folder ``datas/benchmark_realworld``:
177 keyframe scans of a spinning LiDAR, binary PCD in the body frame, already deskewed, and
``alidarPose.csv``, one 4x4 body->world pose per keyframe with its time in element [3, 3]). It is
GPL-2.0 and stays out of this repository: give ``--data`` the folder, or a git mirror of the
repository (read with ``git archive``).

The dataset's poses are odometry-grade, not truth. The export treats them as the "true"
trajectory ``T0`` (interpolated to 100 Hz) and adds kinreg's simulated drift ``D(t)`` on top:

- each point of keyframe k gets a time from its azimuth within the keyframe's 0.1 s sweep
  (the sweep ends at the keyframe's time);
- its position on the dataset's poses is ``p_w = T0(t_k) p_body``; exported, it is
  ``D(t_p) p_w`` with the drift ``D = T_drifted T0^-1`` at the point's own time, so that the
  exported trajectory and cloud agree as a kinematic scanner's do.

The figure of merit is the median plane thickness of 1 m cells (``kinreg.report.thickness``)
of a cloud over that of the cloud on the dataset's own poses: below 1.0 the cloud is crisper
than the dataset's poses make it (a method that also removes the dataset's own odometry drift).

    python benchmarks/real_hall.py run --data /path/to/BALM --work /tmp/real_hall \\
        --results benchmarks/results/real_hall.json
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import math
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import numpy as np

from kinreg.geometry import Pose, make_quat_continuous, matrix_to_quat
from kinreg.report.cloud_views import MIN_CELL_POINTS
from kinreg.report.thickness import CellMoments, compare
from kinreg.simulation.drift import DriftConfig, DriftModel, drifted_trajectory
from kinreg.simulation.files import write_trajectory_geoslam
from kinreg.types import Trajectory

FOLDER = "datas/benchmark_realworld"
SWEEP_S = 0.1
RATE_HZ = 100.0
CELL_M = 1.0
MAGNITUDES = ((0.1, 0.5), (0.2, 1.0), (0.5, 2.0))  # position m, rotation deg over the whole run
MODELS = ("slam", "gnss-ins", "world")


@dataclasses.dataclass(frozen=True)
class Hall:
    """The dataset: keyframe times and poses (body->world) and every keyframe's points."""

    stamps_s: np.ndarray  # (K,)
    T_world_body: np.ndarray  # (K, 4, 4)
    points_body: list[np.ndarray]  # K arrays (n_k, 3), float64
    intensity: list[np.ndarray]


def _read_pcd(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """x, y, z, intensity of a binary PCD whose fields are all 4-byte floats."""
    end = 0
    fields: list[str] = []
    n = 0
    for _ in range(20):
        nl = data.index(b"\n", end)
        line = data[end:nl].decode("ascii").strip()
        end = nl + 1
        key, _, rest = line.partition(" ")
        if key == "FIELDS":
            fields = rest.split()
        elif key == "POINTS":
            n = int(rest)
        elif key == "DATA":
            if rest.strip() != "binary":
                raise ValueError(f"PCD DATA {rest!r}: only binary is read")
            break
    rec = np.frombuffer(data, dtype=np.float32, count=n * len(fields), offset=end).reshape(n, len(fields))
    xyz = rec[:, [fields.index(c) for c in "xyz"]].astype(np.float64)
    inten = rec[:, fields.index("intensity")] if "intensity" in fields else np.zeros(n, np.float32)
    ok = np.all(np.isfinite(xyz), axis=1) & (np.linalg.norm(xyz, axis=1) > 0.1)
    return xyz[ok], inten[ok]


def _files(data: Path) -> dict[str, bytes]:
    """The dataset's files by name, from a folder or a git mirror of the repository."""
    if (data / "alidarPose.csv").exists():
        return {p.name: p.read_bytes() for p in data.iterdir() if p.suffix in (".csv", ".pcd")}
    if (data / FOLDER / "alidarPose.csv").exists():
        return _files(data / FOLDER)
    tar = subprocess.run(["git", f"--git-dir={data}", "archive", "HEAD", FOLDER], capture_output=True, check=True)
    out = {}
    with tarfile.open(fileobj=io.BytesIO(tar.stdout)) as t:
        for m in t.getmembers():
            if m.isfile():
                f = t.extractfile(m)
                assert f is not None
                out[Path(m.name).name] = f.read()
    return out


def read_hall(data: Path) -> Hall:
    files = _files(data)
    rows = np.array([[float(v) for v in line.strip().rstrip(",").split(",")]
                     for line in files["alidarPose.csv"].decode().splitlines() if line.strip()])
    T = rows.reshape(-1, 4, 4).copy()
    stamps = T[:, 3, 3].copy()
    T[:, 3, :] = (0.0, 0.0, 0.0, 1.0)
    pts, inten = [], []
    for k in range(len(T)):
        xyz, i = _read_pcd(files[f"full{k}.pcd"])
        pts.append(xyz)
        inten.append(i)
    return Hall(stamps, T, pts, inten)


def reference_trajectory(hall: Hall) -> Trajectory:
    """The dataset's poses at 100 Hz (C2 in position and attitude), from the first sweep's start."""
    from scipy.interpolate import CubicSpline
    from scipy.spatial.transform import Rotation, RotationSpline

    t0, t1 = hall.stamps_s[0] - SWEEP_S, hall.stamps_s[-1]
    stamps = t0 + np.arange(math.ceil((t1 - t0) * RATE_HZ) + 1) / RATE_HZ
    rot = Rotation.from_matrix(hall.T_world_body[:, :3, :3])
    # extrapolate the first 0.1 s with the first keyframe's pose
    q_t = np.clip(stamps, hall.stamps_s[0], hall.stamps_s[-1])
    R = RotationSpline(hall.stamps_s, rot)(q_t).as_matrix()
    xyz = CubicSpline(hall.stamps_s, hall.T_world_body[:, :3, 3])(q_t)
    quat = make_quat_continuous(matrix_to_quat(R))
    return Trajectory(stamps, Pose(quat, xyz), source="real hall (dataset poses)")


def point_times(hall: Hall) -> list[np.ndarray]:
    """Per keyframe, each point's time from its azimuth: the sweep's 0.1 s ending at the keyframe."""
    out = []
    for t_k, xyz in zip(hall.stamps_s, hall.points_body, strict=True):
        frac = (np.arctan2(xyz[:, 1], xyz[:, 0]) + np.pi) / (2 * np.pi)
        out.append(t_k - SWEEP_S + SWEEP_S * np.clip(frac, 0.0, 1.0 - 1e-9))
    return out


def world_points(hall: Hall) -> np.ndarray:
    """Every point on the dataset's own poses, (N, 3)."""
    return np.concatenate([xyz @ T[:3, :3].T + T[:3, 3] for T, xyz in zip(hall.T_world_body, hall.points_body,
                                                                           strict=True)])


def write_laz(path: Path, xyz: np.ndarray, stamps: np.ndarray, intensity: np.ndarray) -> None:
    import laspy

    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([1e-4, 1e-4, 1e-4])
    header.offsets = np.round(np.median(xyz[:: max(1, len(xyz) // 10000)], axis=0))
    header.generating_software = "kinreg benchmarks/real_hall.py"
    with laspy.open(path, mode="w", header=header, do_compress=path.suffix == ".laz") as w:
        for a in range(0, len(xyz), 2_000_000):
            s = slice(a, a + 2_000_000)
            rec = laspy.ScaleAwarePointRecord.zeros(len(xyz[s]), header=w.header)
            rec.x, rec.y, rec.z = xyz[s, 0], xyz[s, 1], xyz[s, 2]
            rec.gps_time = stamps[s]
            rec.intensity = np.clip(intensity[s], 0, 65535).astype(np.uint16)
            rec.return_number = np.ones(len(rec), np.uint8)
            rec.number_of_returns = np.ones(len(rec), np.uint8)
            w.write_points(rec)


def export(hall: Hall, ref: Trajectory, times: np.ndarray, p_world: np.ndarray, intensity: np.ndarray,
           model: str, pos_m: float, rot_deg: float, seed: int, out: Path) -> Trajectory:
    """Write ``out/trajectory.txt`` and ``out/cloud.laz``: the hall with drift on top; returns the
    drifted trajectory."""
    out.mkdir(parents=True, exist_ok=True)
    duration = float(ref.stamps_s[-1] - ref.stamps_s[0])
    config = DriftConfig(pos_m, rot_deg, model=DriftModel(model), at_s=duration)
    drifted, drift = drifted_trajectory(ref, config, np.random.default_rng(seed))
    order = np.argsort(times, kind="stable")
    t = times[order]
    D = Trajectory(ref.stamps_s, drift, source="drift").pose_at(t)
    xyz = D.apply(p_world[order])
    write_trajectory_geoslam(out / "trajectory.txt", drifted)
    write_laz(out / "cloud.laz", xyz, t, intensity[order])
    return drifted


def moments_of(xyz_chunks, origin: np.ndarray) -> CellMoments:
    m = CellMoments(origin, CELL_M)
    for xyz in xyz_chunks:
        m.add(xyz)
    return m


def laz_chunks(path: Path):
    import laspy

    with laspy.open(path) as r:
        for chunk in r.chunk_iterator(2_000_000):
            yield np.stack([chunk.x, chunk.y, chunk.z], axis=1).astype(np.float64)


def rigid_fit_rms_mm(est: np.ndarray, truth: np.ndarray) -> float:
    """RMS [mm] of ``truth - est`` (n, 3) after the rigid fit of ``est`` onto ``truth``."""
    a, b = est - est.mean(0), truth - truth.mean(0)
    U, _, Vt = np.linalg.svd(a.T @ b)
    S = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
    res = b - a @ (U @ S @ Vt)
    return float(np.sqrt(np.mean(np.sum(res**2, axis=1))) * 1000)


def station_agreement(stations_csv: Path, ref: Trajectory, drifted: Trajectory) -> tuple[float, float]:
    """RMS [mm] after a rigid fit of the adjusted stations' positions, and of the drifted
    trajectory's at the same times, against the dataset's poses (odometry-grade: a figure of
    agreement, not of accuracy)."""
    rows = np.genfromtxt(stations_csv, delimiter=",", names=True)
    quasi = np.isfinite(rows["t"])
    t = np.clip(rows["t"][quasi], ref.stamps_s[0], ref.stamps_s[-1])
    adjusted = np.stack([rows["x"], rows["y"], rows["z"]], axis=1)[quasi]
    truth = ref.pose_at(t).t_xyz
    return rigid_fit_rms_mm(adjusted, truth), rigid_fit_rms_mm(drifted.pose_at(t).t_xyz, truth)


def run_one(case: dict, hall: Hall, ref: Trajectory, times: np.ndarray, p_world: np.ndarray,
            intensity: np.ndarray, ref_moments: CellMoments, origin: np.ndarray, work: Path,
            config: Path | None, keep: bool) -> dict:
    folder = work / f"{case['model']}_{case['pos_m']}_{case['seed']}"
    drifted = export(hall, ref, times, p_world, intensity, case["model"], case["pos_m"], case["rot_deg"],
                     case["seed"], folder)
    cmd = [sys.executable, "-m", "kinreg_cli", "process", "--trajectory", str(folder / "trajectory.txt"),
           "--cloud", str(folder / "cloud.laz"), "--out", str(folder / "out"), "--overwrite"]
    if config is not None:
        cmd += ["--config", str(config)]
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    result = dict(case, exit_code=proc.returncode, seconds=round(time.perf_counter() - start, 1),
                  last_line=(proc.stderr.strip().splitlines() or [""])[-1][:400])
    input_ratio = compare(ref_moments, moments_of(laz_chunks(folder / "cloud.laz"), origin),
                          MIN_CELL_POINTS).figures["median_ratio_after_before"]
    result["thickness_input_over_dataset"] = round(input_ratio, 4)
    report = folder / "out" / "report.json"
    if proc.returncode == 0 and report.exists():
        rep = json.loads(report.read_text())
        after = compare(ref_moments, moments_of(laz_chunks(folder / "out" / "corrected.laz"), origin),
                        MIN_CELL_POINTS).figures
        result["thickness_corrected_over_dataset"] = round(after["median_ratio_after_before"], 4)
        adj, links = rep.get("adjustment", {}), rep.get("links", {})
        result["status"] = adj.get("status")
        result["sigma0"] = adj.get("sigma0")
        result["redundancy"] = adj.get("redundancy")
        result["links"] = dict(links.get("by_status", {}), sigma0=links.get("sigma0"))
        result["position_sigma_mm"] = rep.get("stations", {}).get("position_sigma_mm")
        result["links_model"] = links.get("model")
        result["window_s"] = rep.get("slicing", {}).get("window_s")
        adjusted_mm, input_mm = station_agreement(folder / "out" / "stations.csv", ref, drifted)
        result["stations_rigid_rms_mm"] = round(adjusted_mm, 1)
        result["stations_rigid_rms_mm_input"] = round(input_mm, 1)
    if not keep:
        for p in (folder / "cloud.laz", folder / "out" / "corrected.laz", folder / "out" / "sequence.e57"):
            p.unlink(missing_ok=True)
    return result


def summary(results: Path) -> str:
    """The results' table in Markdown: per drift model and magnitude, the runs' figures."""
    cases = json.loads(results.read_text())["cases"]
    lines = ["| drift | magnitude | runs | results | input / corrected thickness (per seed) | windows [s] | "
             "links ok / rejected |",
             "|---|---|---:|---:|---|---|---|"]
    for model in MODELS:
        for pos, rot in MAGNITUDES:
            runs = [c for c in cases if c["model"] == model and c["pos_m"] == pos]
            if not runs:
                continue
            ok = [c for c in runs if c["exit_code"] == 0 and "thickness_corrected_over_dataset" in c]
            pairs = ", ".join(f"{c['thickness_input_over_dataset']:.3f} / {c['thickness_corrected_over_dataset']:.3f}"
                              for c in ok)
            windows = ", ".join(f"{c['window_s']:g}" for c in ok)
            links = ", ".join(f"{c['links'].get('ok')} / {c['links'].get('rejected')}" for c in ok)
            lines.append(f"| {model} | {pos} m / {rot} deg | {len(runs)} | {len(ok)} | {pairs} | {windows} | {links} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    table = sub.add_parser("summary", help="print the results' table (Markdown)")
    table.add_argument("results", type=Path, nargs="?", default=Path(__file__).parent / "results" / "real_hall.json")
    for name in ("export", "run"):
        p = sub.add_parser(name)
        p.add_argument("--data", type=Path, required=True, help="the dataset folder or a git mirror of BALM")
        p.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
        p.add_argument("--magnitudes", nargs="+", type=int, default=[0, 1, 2],
                       help="indices into 0.1 m/0.5 deg, 0.2 m/1 deg, 0.5 m/2 deg")
        p.add_argument("--seeds", nargs="+", type=int, default=[1, 2, 3])
        p.add_argument("--work", type=Path, required=True)
    run = sub.choices["run"]
    run.add_argument("--config", type=Path, default=None, help="a kinreg config (default: kinreg's defaults)")
    run.add_argument("--results", type=Path, default=Path(__file__).parent / "results" / "real_hall.json")
    run.add_argument("--keep", action="store_true", help="keep the clouds of every run")
    args = ap.parse_args()
    if args.command == "summary":
        print(summary(args.results))
        return
    hall = read_hall(args.data)
    ref = reference_trajectory(hall)
    times = np.concatenate(point_times(hall))
    p_world = world_points(hall)
    intensity = np.concatenate(hall.intensity)
    print(f"real hall: {len(hall.stamps_s)} keyframes, {len(p_world):,} points, "
          f"{ref.stamps_s[-1] - ref.stamps_s[0]:.1f} s", flush=True)
    # seed by seed: the first seed's whole matrix before the next
    cases = [dict(model=m, pos_m=MAGNITUDES[g][0], rot_deg=MAGNITUDES[g][1], seed=s)
             for s in args.seeds for g in args.magnitudes for m in args.models]
    if args.command == "export":
        for c in cases:
            folder = args.work / f"{c['model']}_{c['pos_m']}_{c['seed']}"
            export(hall, ref, times, p_world, intensity, c["model"], c["pos_m"], c["rot_deg"], c["seed"], folder)
            print("wrote", folder, flush=True)
        return
    origin = p_world.min(axis=0)
    ref_moments = moments_of([p_world], origin)
    args.results.parent.mkdir(parents=True, exist_ok=True)
    # the runs of an earlier, interrupted call with the same cases are kept, not run again
    results = json.loads(args.results.read_text())["cases"] if args.results.exists() else []
    done = {(r["model"], r["pos_m"], r["seed"]) for r in results}
    for c in cases:
        if (c["model"], c["pos_m"], c["seed"]) in done:
            continue
        r = run_one(c, hall, ref, times, p_world, intensity, ref_moments, origin, args.work, args.config, args.keep)
        results.append(r)
        print(json.dumps(r), flush=True)
        args.results.write_text(json.dumps({"cases": results, "config": str(args.config or "defaults")}, indent=1))


if __name__ == "__main__":
    main()
