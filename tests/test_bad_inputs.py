"""A catalogue of bad inputs, run through the ``kinreg`` entry point.

Every case must end with exit code 1 and one line ``kinreg: error: FILE: PROBLEM`` on stderr
(no traceback), and must leave no output and no temporary ``.*.tmp-*`` file behind. The stage
cache (``.kinreg-cache/``) of stages that finished before the failure may stay: it is what
``--resume`` continues from. Rich progress
bars of stages that finished before the failure may precede the error line (they are drawn on
stderr); they are the only other lines allowed. Log warnings go to pytest's log capture in-process,
and are checked separately where a case is about a warning.

Cases that need the pipeline (``kinreg process --static/--reference``, datum and network checks)
are marked ``xfail(strict=True)`` with what is missing; they turn into failures as soon as the
pipeline handles them, so the mark has to be removed then.
"""

from __future__ import annotations

import csv
import errno
import json
import logging
import os
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import laspy
import numpy as np
import pytest
from clirunner import run_cli
from conftest import SyntheticRun, write_synthetic_run
from e57fixtures import write_raw_e57_scan
from kinreg_cli.main import main

from kinreg.geometry import Pose, rotvec_to_quat
from kinreg.io import atomic, direct_io, e57_writer
from kinreg.io.e57_writer import write_e57_sequence
from kinreg.io.trajectory import write_trajectory_geoslam
from kinreg.run import spill as slicing
from kinreg.types import Scan, ScanKind, Trajectory

ERROR_PREFIX = "kinreg: error: "


# --------------------------------------------------------------------------- helpers




def message_lines(err: str) -> list[str]:
    """stderr without the progress bars of finished stages (rich draws them with '━')."""
    return [line for line in err.splitlines() if line.strip() and "━" not in line]


def files_under(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.is_file()) if folder.exists() else []


def result_files(folder: Path) -> list[Path]:
    """Files under ``folder`` outside the stage cache."""
    return [p for p in files_under(folder) if ".kinreg-cache" not in p.relative_to(folder).parts]


@dataclass
class Case:
    """One bad input: the command line, the file to be named, what the problem must say."""

    args: list[object]
    bad: Path | None  # the file the message must name (None: no file involved)
    reason: str  # regular expression the text after "FILE: " must match
    out: Path  # the output (file or folder) that must not appear
    keep: dict[Path, bytes] = field(default_factory=dict)  # files that must be left untouched


@dataclass
class Env:
    tmp: Path
    run: SyntheticRun
    monkeypatch: pytest.MonkeyPatch

    @property
    def out_dir(self) -> Path:
        return self.tmp / "out"

    @property
    def seq(self) -> Path:
        return self.out_dir / "seq.e57"

    def slice_args(self, trajectory: Path | None = None, cloud: Path | None = None, *extra: object) -> list[object]:
        return ["slice", "-t", trajectory or self.run.trajectory_path, "-c", cloud or self.run.cloud_path,
                "-o", self.seq, *extra]

    def process_args(self, *extra: object) -> list[object]:
        return ["process", "-t", self.run.trajectory_path, "-c", self.run.cloud_path, "-o", self.out_dir, *extra]

    def traj_lines(self) -> list[str]:
        return self.run.trajectory_path.read_text().splitlines()

    def write(self, name: str, content: str | bytes) -> Path:
        path = self.tmp / name
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            path.write_text(content)
        return path

    def bad_trajectory(self, edit: Callable[[list[str]], list[str]], name: str = "bad_traj.txt") -> Case:
        path = self.write(name, "\n".join(edit(self.traj_lines())) + "\n")
        return Case(self.slice_args(trajectory=path), path, "", self.seq)


@pytest.fixture(scope="module")
def base_run(tmp_path_factory: pytest.TempPathFactory) -> SyntheticRun:
    # 12 s of trajectory (1201 rows, line 1 is the header) and 60,000 time-sorted points: enough
    # for planes in windows of 2.5 s.
    return write_synthetic_run(tmp_path_factory.mktemp("bad_inputs") / "run", n_points=60_000, duration_s=12.0)


def _set_field(line: str, index: int, value: str) -> str:
    fields = line.split()
    fields[index] = value
    return " ".join(fields)


def _scan(points: int = 3000, stamps: bool = True, pose: Pose | None = None) -> Scan:
    rng = np.random.default_rng(11)
    t0 = 1623220971.15523
    return Scan(
        scan_id=0,
        name="static_A",
        kind=ScanKind.STATIC,
        T_obj_scan=pose if pose is not None else Pose.identity(),
        points_xyz=rng.uniform(-5.0, 5.0, (points, 3)),
        stamps_s=np.sort(t0 + rng.uniform(0.0, 5.0, points)) if stamps else None,
    )


def _write_e57_without_pose(path: Path) -> None:
    """A static scan as many scanners' exports have it: cartesian points, no ``pose`` element."""
    xyz = np.random.default_rng(3).uniform(-5.0, 5.0, (200, 3))
    write_raw_e57_scan(path, "tls_without_pose", {f"cartesian{c}": xyz[:, i] for i, c in enumerate("XYZ")})


def _write_corridor(folder: Path) -> None:
    """``traj.txt`` and ``cloud.laz`` in ``folder``: 12 s walking along a corridor (x), whose walls
    (y = -1.5, 1.5), floor (z = 0) and ceiling (z = 2.5) fix only the y and z directions."""
    rng = np.random.default_rng(1)
    t0, duration = 1623220971.0, 12.0
    t = t0 + np.arange(0.0, duration + 1e-9, 0.01)
    s = t - t0
    traj = Trajectory(t, Pose(rotvec_to_quat(np.column_stack([0 * s, 0 * s, 0.05 * np.sin(0.3 * s)])),
                              np.column_stack([0.4 * s, 0.1 * np.sin(0.5 * s), 1.5 + 0 * s])))
    write_trajectory_geoslam(folder / "traj.txt", traj)
    n = 80_000
    stamps = np.sort(rng.uniform(t0, t0 + duration, n))
    face = rng.integers(0, 4, n)
    xyz = np.column_stack([
        0.4 * (stamps - t0) + rng.uniform(-6.0, 6.0, n),
        np.where(face == 0, -1.5, np.where(face == 1, 1.5, rng.uniform(-1.5, 1.5, n))),
        np.where(face == 2, 0.0, np.where(face == 3, 2.5, rng.uniform(0.0, 2.5, n))),
    ]) + rng.normal(0.0, 0.003, (n, 3))
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([1e-4, 1e-4, 1e-4])
    header.offsets = np.floor(xyz.min(axis=0))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.gps_time = stamps
    las.write(folder / "cloud.laz")


CORRIDOR_REFERENCE = """plane_construction_accuracy_m = 0.005
[[plane]]
name = "south"
axis = "y"
offset_m = -1.5
normal_sign = 1
[[plane]]
name = "north"
axis = "y"
offset_m = 1.5
normal_sign = -1
[[plane]]
name = "floor"
axis = "z"
offset_m = 0.0
normal_sign = 1
[[plane]]
name = "ceiling"
axis = "z"
offset_m = 2.5
normal_sign = -1
"""


REFERENCE_OK = """plane_construction_accuracy_m = 0.05
[[plane]]
name = "floor"
axis = "z"
offset_m = 0.0
normal_sign = 1
"""


# --------------------------------------------------------------------------- the cases


def empty_trajectory(env: Env) -> Case:
    path = env.write("empty.txt", "")
    return Case(env.slice_args(trajectory=path), path, r"0 pose row\(s\); a trajectory needs at least two", env.seq)


def header_only_trajectory(env: Env) -> Case:
    path = env.write("header_only.txt", "%time x y z q0 q1 q2 q3\n")
    return Case(env.slice_args(trajectory=path), path, r"0 pose row\(s\)", env.seq)


def one_row_trajectory(env: Env) -> Case:
    case = env.bad_trajectory(lambda lines: lines[:2])
    case.reason = r"1 pose row\(s\); a trajectory needs at least two"
    return case


def non_numeric_row(env: Env) -> Case:
    case = env.bad_trajectory(lambda lines: [*lines[:10], _set_field(lines[10], 2, "oops"), *lines[11:]])
    case.reason = r"^row 11: 'oops' is not a number$"
    return case


def nan_row(env: Env) -> Case:
    case = env.bad_trajectory(lambda lines: [*lines[:20], _set_field(lines[20], 3, "nan"), *lines[21:]])
    case.reason = r"^row 21: value is not finite \(NaN or infinite\)$"
    return case


def infinite_row(env: Env) -> Case:
    case = env.bad_trajectory(lambda lines: [*lines[:30], _set_field(lines[30], 1, "-inf"), *lines[31:]])
    case.reason = r"^row 31: value is not finite"
    return case


def duplicate_time(env: Env) -> Case:
    def edit(lines: list[str]) -> list[str]:
        lines[41] = _set_field(lines[41], 0, lines[40].split()[0])
        return lines

    case = env.bad_trajectory(edit)
    case.reason = r"^row 42: time [0-9.]+ repeats the previous row's [0-9.]+; times must increase strictly$"
    return case


def decreasing_time(env: Env) -> Case:
    def edit(lines: list[str]) -> list[str]:
        lines[50], lines[51] = lines[51], lines[50]
        return lines

    case = env.bad_trajectory(edit)
    case.reason = r"^row 52: time [0-9.]+ goes back from the previous row's [0-9.]+; times must increase strictly$"
    return case


def non_unit_quaternion(env: Env) -> Case:
    def edit(lines: list[str]) -> list[str]:
        f = lines[60].split()
        f[4:8] = [f"{1.1 * float(v):.9f}" for v in f[4:8]]  # norm 1.1, far beyond the 1e-3 tolerance
        lines[60] = " ".join(f)
        return lines

    case = env.bad_trajectory(edit)
    case.reason = r"^row 61: quaternion norm 1\.100000 is not 1 \(tolerance 0\.001\)$"
    return case


def short_row(env: Env) -> Case:
    case = env.bad_trajectory(lambda lines: [*lines[:5], " ".join(lines[5].split()[:5]), *lines[6:]])
    case.reason = r"^row 6: 5 values, expected at least 8$"
    return case


def binary_trajectory(env: Env) -> Case:
    path = env.write("binary.txt", bytes(range(128, 256)) * 8)
    return Case(env.slice_args(trajectory=path), path, r"not a text file \(cannot decode as UTF-8\)", env.seq)


def truncated_ply_trajectory(env: Env) -> Case:
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex 100\n"
              + "".join(f"property double {n}\n" for n in ("time", "x", "y", "z", "qw", "qx", "qy", "qz"))
              + "end_header\n")
    path = env.write("cut.ply", header.encode("ascii") + bytes(64 * 37))
    return Case(env.slice_args(trajectory=path), path, r"PLY file ends after 37 of 100 vertices", env.seq)


def csv_without_quaternion(env: Env) -> Case:
    path = env.write("traj.csv", "time,x,y,z\n1,0,0,0\n2,1,0,0\n")
    return Case(env.slice_args(trajectory=path), path, r"no column for 'qw' in the header", env.seq)


def missing_trajectory(env: Env) -> Case:
    path = env.tmp / "missing.txt"
    return Case(env.slice_args(trajectory=path), path, r"^file not found$", env.seq)


def empty_laz(env: Env) -> Case:
    path = env.write("empty.laz", b"")
    return Case(env.slice_args(cloud=path), path, r"^cannot open as LAS/LAZ: ", env.seq)


def garbage_las(env: Env) -> Case:
    path = env.write("garbage.las", b"this is not a LAS file\n" * 100)
    return Case(env.slice_args(cloud=path), path, r"^cannot open as LAS/LAZ: ", env.seq)


def truncated_laz(env: Env) -> Case:
    data = env.run.cloud_path.read_bytes()
    path = env.write("cut.laz", data[: len(data) * 2 // 3])
    return Case(env.slice_args(cloud=path), path, r"truncated", env.seq)


def corrupted_laz_chunk(env: Env) -> Case:
    # 200,000 points: laspy writes LAZ chunks of 50,000 points, so the file has four chunks and the
    # middle of the file is inside the compressed data of the second or third one. Random bytes
    # there make the arithmetic decoder run past its chunk, which lazrs reports. LAZ has no
    # checksums: damage elsewhere can decode silently to wrong values (see the test below).
    run = write_synthetic_run(env.tmp / "big", n_points=200_000, duration_s=12.0)
    data = bytearray(run.cloud_path.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 256] = np.random.default_rng(0).bytes(256)
    path = env.write("corrupted.laz", bytes(data))
    return Case(env.slice_args(trajectory=run.trajectory_path, cloud=path), path,
                r"^decoding failed (after|at point) [0-9,]+ of 200,000 points \(truncated or corrupted\?\): ", env.seq)


def las_without_gps_time(env: Env) -> Case:
    run = write_synthetic_run(env.tmp / "fmt0", n_points=2000, duration_s=12.0, point_format=0, laz=False)
    return Case(env.slice_args(cloud=run.cloud_path), run.cloud_path,
                r"^no gps_time field \(LAS point format 0\); kinreg needs point times$", env.seq)


def unsupported_cloud_format(env: Env) -> Case:
    path = env.write("cloud.xyz", "0 0 0\n")
    return Case(env.slice_args(cloud=path), path, r"unsupported point cloud format '\.xyz'", env.seq)


def missing_cloud(env: Env) -> Case:
    path = env.tmp / "missing.laz"
    return Case(env.slice_args(cloud=path), path, r"^file not found$", env.seq)


def empty_e57(env: Env) -> Case:
    path = env.write("empty.e57", b"")
    return Case(env.slice_args(cloud=path), path, r"not an E57 file", env.seq)


def e57_without_timestamp(env: Env) -> Case:
    path = env.tmp / "untimed.e57"
    write_e57_sequence(path, [_scan(stamps=False)])
    return Case(env.slice_args(cloud=path), path,
                r"^no per-point timeStamp field in scan 0 \('static_A'\); kinreg needs point times$", env.seq)


def truncated_e57(env: Env) -> Case:
    full = env.tmp / "full.e57"
    write_e57_sequence(full, [_scan()])
    data = full.read_bytes()
    path = env.write("cut.e57", data[: len(data) // 2])
    return Case(env.slice_args(cloud=path), path, r"truncated", env.seq)


def no_time_overlap(env: Env) -> Case:
    # The trajectory is shifted by one hour: not a single point time falls inside it.
    def edit(lines: list[str]) -> list[str]:
        return [lines[0]] + [_set_field(line, 0, f"{float(line.split()[0]) + 3600.0:.6f}") for line in lines[1:]]

    path = env.bad_trajectory(edit, "shifted.txt").bad
    assert path is not None
    return Case(env.slice_args(trajectory=path), env.run.cloud_path,
                r"^point times [0-9.]+ \.\. [0-9.]+ s do not fit the trajectory's [0-9.]+ \.\. [0-9.]+ s "
                r"\(100\.0 % outside\); no recognised time-base offset", env.seq)


def windows_give_no_scan(env: Env) -> Case:
    cfg = env.write("k.toml", "[slicing]\nmin_points = 50000\n")
    return Case([*env.slice_args(), "--config", cfg], env.run.cloud_path,
                r"^no window has at least 50000 points \(2 windows\); use longer windows or a smaller min_points$",
                env.seq)


def config_syntax_error(env: Env) -> Case:
    cfg = env.write("k.toml", "[slicing\nwindow_s = 4\n")
    return Case([*env.slice_args(), "--config", cfg], cfg, r"^invalid TOML: ", env.seq)


def config_unknown_key(env: Env) -> Case:
    cfg = env.write("k.toml", "[slicing]\nwindow = 4\n")
    return Case([*env.slice_args(), "--config", cfg], cfg, r"^\[slicing\]: unknown key\(s\) window \(known: ", env.seq)


def config_wrong_type(env: Env) -> Case:
    cfg = env.write("k.toml", '[slicing]\nwindow_s = "six"\n')
    return Case([*env.slice_args(), "--config", cfg], cfg, r"^\[slicing\] window_s: expected a number, got 'six'$",
                env.seq)


def config_missing(env: Env) -> Case:
    cfg = env.tmp / "missing.toml"
    return Case(["config", "--config", cfg], cfg, r"^file not found$", env.out_dir)


def negative_window_on_command_line(env: Env) -> Case:
    return Case([*env.slice_args(), "--window-s", "-1"], None, r"^\[slicing\] window_s: must be positive, got -1\.0$",
                env.seq)


def spill_folder_missing(env: Env) -> Case:
    missing = env.tmp / "no_such_folder"
    cfg = env.write("k.toml", f'[slicing]\ntemp_dir = "{missing}"\n')
    return Case([*env.slice_args(), "--config", cfg], missing,
                r"^\[slicing\] temp_dir: cannot create the spill folder: No such file or directory$", env.seq)


def output_exists(env: Env) -> Case:
    env.out_dir.mkdir()
    env.seq.write_bytes(b"precious")
    return Case(env.slice_args(), env.seq, r"^exists; use --overwrite to replace it$", env.seq,
                keep={env.seq: b"precious"})


def output_is_a_folder(env: Env) -> Case:
    env.seq.mkdir(parents=True)
    return Case([*env.slice_args(), "--overwrite"], env.seq, r"^is a folder$", env.seq / "x")


def output_folder_holds_results(env: Env) -> Case:
    env.out_dir.mkdir()
    (env.out_dir / "stations.csv").write_text("old results\n")
    return Case(env.process_args(), env.out_dir,
                r"^already holds kinreg results; use --overwrite to replace them or --resume to update them$",
                env.out_dir / "report.json", keep={env.out_dir / "stations.csv": b"old results\n"})


def output_folder_holds_unfinished_run(env: Env) -> Case:
    (env.out_dir / ".kinreg-cache").mkdir(parents=True)
    return Case(env.process_args(), env.out_dir,
                r"^holds an unfinished kinreg run; use --resume to continue it or --overwrite to start afresh$",
                env.out_dir / "report.json")


def resume_in_a_folder_without_kinreg_run(env: Env) -> Case:
    env.out_dir.mkdir()
    (env.out_dir / "notes.txt").write_text("not kinreg's\n")
    return Case(env.process_args("--resume"), env.out_dir,
                r"^holds no kinreg run to resume \(no results, no \.kinreg-cache\); check --out or leave out --resume$",
                env.out_dir / "report.json", keep={env.out_dir / "notes.txt": b"not kinreg's\n"})


def resume_and_overwrite(env: Env) -> Case:
    return Case(env.process_args("--resume", "--overwrite"), None, r"^--resume and --overwrite exclude each other",
                env.out_dir / "report.json")


def output_under_a_file(env: Env) -> Case:
    # root ignores permissions, so "cannot write here" is made with a path below a regular file.
    blocker = env.write("file.txt", "not a folder\n")
    out = blocker / "sub" / "seq.e57"
    return Case(["slice", "-t", env.run.trajectory_path, "-c", env.run.cloud_path, "-o", out], blocker / "sub",
                r"^cannot create the folder: Not a directory$", out, keep={blocker: b"not a folder\n"})


def output_folder_not_writable(env: Env) -> Case:
    # root may write anywhere; pretend the output folder is read-only (and only that folder).
    real_access = os.access
    out_dir = env.out_dir

    def access(path: object, mode: int, *args: object, **kwargs: object) -> bool:
        return False if Path(str(path)) == out_dir else real_access(path, mode, *args, **kwargs)  # type: ignore

    env.monkeypatch.setattr(atomic.os, "access", access)
    return Case(env.slice_args(), env.out_dir, r"^folder is not writable$", env.seq)


def disk_full_while_spilling(env: Env) -> Case:
    def full(self: object, unit: int, records: np.ndarray) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    env.monkeypatch.setattr(slicing._SpillWriter, "append", full)
    spill = env.tmp / "spill"
    spill.mkdir()
    cfg = env.write("k.toml", f'[slicing]\ntemp_dir = "{spill}"\n')
    return Case([*env.slice_args(), "--config", cfg], spill,
                r"^disk full while spilling points to the temporary folder after [0-9,]+ points ", env.seq)


def disk_full_while_writing_e57(env: Env) -> Case:
    # Small file buffers: the E57 file goes out in many writes, and the disk fills after the first.
    env.monkeypatch.setattr(e57_writer, "FILE_BUFFER_BYTES", 4096)
    original = direct_io._write_all
    calls: list[int] = []

    def write_then_fail(fd: int, view: memoryview) -> None:
        calls.append(len(view))
        if len(calls) >= 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        original(fd, view)

    env.monkeypatch.setattr(direct_io, "_write_all", write_then_fail)
    return Case(env.slice_args(), env.seq,
                r"^cannot (write scan 'qs_\d+'|finish E57 file): No space left on device$", env.seq)


def disk_full_while_writing_text(env: Env) -> Case:
    # kinreg link writes planes.csv and links.csv through atomic_path; the disk fills half-way.
    original = Path.write_text

    def half_then_full(self: Path, data: str, *args: object, **kwargs: object) -> int:
        original(self, data[: len(data) // 2], *args, **kwargs)  # type: ignore[arg-type]
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self))

    env.monkeypatch.setattr(Path, "write_text", half_then_full)
    return Case(["link", "-t", env.run.trajectory_path, "-c", env.run.cloud_path, "-o", env.out_dir],
                env.out_dir / "planes.csv", r"^disk full while writing$", env.out_dir / "planes.csv")


# --- cases through kinreg process: reference planes, static scans, the network


def reference_missing(env: Env) -> Case:
    path = env.tmp / "missing.toml"
    return Case(env.process_args("--reference", path), path, r"^reference-plane file not found$", env.out_dir / "x")


def reference_syntax_error(env: Env) -> Case:
    path = env.write("ref.toml", "plane_construction_accuracy_m = \n")
    return Case(env.process_args("--reference", path), path, r"^TOML syntax error: ", env.out_dir / "x")


def reference_unknown_axis(env: Env) -> Case:
    path = env.write("ref.toml", REFERENCE_OK.replace('axis = "z"', 'axis = "w"'))
    return Case(env.process_args("--reference", path), path, r"^plane 'floor': unknown axis 'w'", env.out_dir / "x")


def reference_duplicate_name(env: Env) -> Case:
    path = env.write("ref.toml", REFERENCE_OK + REFERENCE_OK.split("\n", 1)[1])
    return Case(env.process_args("--reference", path), path, r"^duplicate plane name 'floor'$", env.out_dir / "x")


def singular_datum(env: Env) -> Case:
    # The only datum are the corridor's reference planes: walls and floor fix y, z and the three
    # rotations, nothing fixes x (along the corridor).
    _write_corridor(env.tmp)
    path = env.write("ref.toml", CORRIDOR_REFERENCE)
    return Case(["process", "-t", env.tmp / "traj.txt", "-c", env.tmp / "cloud.laz", "-o", env.out_dir,
                 "--window-s", "4", "--reference", path], path, r"datum", env.out_dir / "stations.csv")


def static_scan_without_pose(env: Env) -> Case:
    path = env.tmp / "static.e57"
    _write_e57_without_pose(path)
    return Case(env.process_args("--static", path), path, r"scan 0 \('tls_without_pose'\) has no pose",
                env.out_dir / "x")


def disconnected_network(env: Env) -> Case:
    # A static scan 1 km away shares no plane with the run: the network has two parts, the static
    # one without datum. kinreg must name the parts (or adjust each, if so configured).
    path = env.tmp / "far.e57"
    write_e57_sequence(path, [_scan(stamps=False, pose=Pose(np.array([1.0, 0, 0, 0]), np.array([1000.0, 0, 0])))])
    return Case(env.process_args("--static", path), None,
                r"^the network falls apart: 1 part\(s\) are not linked to the datum \(qs_\d+\.\.qs_\d+\); set "
                r"\[block\] disconnected = \"fix_each\"", env.out_dir / "x")


CASES = [
    # trajectory
    empty_trajectory, header_only_trajectory, one_row_trajectory, non_numeric_row, nan_row, infinite_row,
    duplicate_time, decreasing_time, non_unit_quaternion, short_row, binary_trajectory, truncated_ply_trajectory,
    csv_without_quaternion, missing_trajectory,
    # point cloud
    empty_laz, garbage_las, truncated_laz, corrupted_laz_chunk, las_without_gps_time, unsupported_cloud_format,
    missing_cloud, empty_e57, e57_without_timestamp, truncated_e57,
    # trajectory against cloud, windows
    no_time_overlap, windows_give_no_scan,
    # configuration
    config_syntax_error, config_unknown_key, config_wrong_type, config_missing, negative_window_on_command_line,
    spill_folder_missing,
    # outputs
    output_exists, output_is_a_folder, output_folder_holds_results, output_folder_holds_unfinished_run,
    resume_in_a_folder_without_kinreg_run, resume_and_overwrite, output_under_a_file, output_folder_not_writable,
    disk_full_while_spilling, disk_full_while_writing_e57, disk_full_while_writing_text,
]
PIPELINE_CASES = [
    pytest.param(reference_missing, id="reference_missing"),
    pytest.param(reference_syntax_error, id="reference_syntax_error"),
    pytest.param(reference_unknown_axis, id="reference_unknown_axis"),
    pytest.param(reference_duplicate_name, id="reference_duplicate_name"),
    pytest.param(static_scan_without_pose, id="static_scan_without_pose"),
    pytest.param(disconnected_network, id="disconnected_network"),
    pytest.param(singular_datum, id="singular_datum"),
]


@pytest.mark.parametrize("make_case", [*(pytest.param(c, id=c.__name__) for c in CASES), *PIPELINE_CASES])
def test_bad_input_is_one_line_exit_1_and_no_output(
    make_case: Callable[[Env], Case], tmp_path: Path, base_run: SyntheticRun, capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    env = Env(tmp_path, base_run, monkeypatch)
    case = make_case(env)
    before = set(result_files(env.out_dir)) | set(case.keep)

    code, _, err = run_cli(case.args, capsys)

    assert "Traceback" not in err
    lines = message_lines(err)
    assert len(lines) == 1, err
    line = lines[0]
    assert code == 1, err
    assert line.startswith(ERROR_PREFIX), line
    message = line[len(ERROR_PREFIX):]
    if case.bad is not None:
        assert message.startswith(f"{case.bad}: "), f"the message does not name {case.bad}: {line}"
        message = message[len(f"{case.bad}: "):]
    assert re.search(case.reason, message), f"{message!r} does not match {case.reason!r}"
    # No output, no temporary file, and the files that were there are untouched.
    assert case.out in case.keep or not case.out.exists()
    assert set(result_files(env.out_dir)) <= before
    assert not [p for p in env.tmp.rglob(".*.tmp-*")]
    for path, content in case.keep.items():
        assert path.read_bytes() == content


def test_catalogue_has_at_least_25_cases() -> None:
    assert len(CASES) + len(PIPELINE_CASES) >= 25


# --------------------------------------------------------------------------- handled, not failed


def test_partial_time_overlap_warns_with_the_share_outside(
    tmp_path: Path, base_run: SyntheticRun, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    """The trajectory covers the first 7.2 s of a 12 s cloud: 40 % of the points are left out, loudly,
    where ``[input] max_dropped_share`` allows it (the default 0.05 refuses, tests/test_input_checks.py)."""
    lines = base_run.trajectory_path.read_text().splitlines()
    short = tmp_path / "short.txt"
    short.write_text("\n".join(lines[:722]) + "\n")  # header + 721 rows at 100 Hz
    out = tmp_path / "out" / "seq.e57"
    cfg = tmp_path / "k.toml"
    cfg.write_text("[input]\nmax_dropped_share = 0.5\n")
    with caplog.at_level(logging.WARNING, logger="kinreg"):
        code, stdout, err = run_cli(["slice", "-t", short, "-c", base_run.cloud_path, "-o", out,
                                     "--config", cfg], capsys)
    assert code == 0, err
    outside = int(np.count_nonzero(base_run.stamps_s > float(lines[721].split()[0])))
    share = 100.0 * outside / len(base_run.stamps_s)
    assert 35.0 < share < 45.0
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(str(base_run.cloud_path) in w and f"{outside} of 60000 points ({share:.1f} %)" in w
               and "outside the trajectory's time range" in w for w in warnings), warnings
    assert f"{outside:,} ({share:.1f} %)" in stdout  # and the summary table repeats it
    assert out.exists()


def test_corridor_scans_with_two_plane_directions_are_linked_through_the_prior(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A corridor (floor, ceiling, two parallel walls) fixes two directions: along the corridor only
    the trajectory prior holds the scans together. kinreg links them and says so in links.csv."""
    _write_corridor(tmp_path)
    code, _, err = run_cli(["link", "-t", tmp_path / "traj.txt", "-c", tmp_path / "cloud.laz",
                            "-o", tmp_path / "out", "--window-s", "4"], capsys)
    assert code == 0, err
    with open(tmp_path / "out" / "links.csv") as f:
        links = list(csv.DictReader(f))
    assert links, "the scans must still be linked"
    for link in links:
        assert link["status"] in ("ok", "prior_only")
        assert int(link["n_directions"]) == 2  # reported: the planes fix two directions only
        assert int(link["rank"]) < 6
        # Along the corridor (x) the link is only as good as the prior; across it the planes rule.
        assert float(link["stx_mm"]) > 2.0 * float(link["sty_mm"])


def test_undetected_laz_corruption_gives_a_complete_output_or_none(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """LAZ has no checksums. Damage inside a chunk's arithmetic-coded bytes is only noticed when
    the decoder runs out of bytes; elsewhere lazrs decodes wrong values without a complaint, and
    no reader can tell. What kinreg guarantees is that it neither crashes nor leaves a half file:
    the run either fails cleanly or writes a complete sequence."""
    run = write_synthetic_run(tmp_path / "run", n_points=200_000, duration_s=12.0)
    data = bytearray(run.cloud_path.read_bytes())
    at = int(len(data) * 0.62)  # with this seed lazrs decodes this damage silently
    data[at : at + 64] = np.random.default_rng(1).bytes(64)
    damaged = tmp_path / "damaged.laz"
    damaged.write_bytes(bytes(data))
    out = tmp_path / "out" / "seq.e57"
    code, _, err = run_cli(["slice", "-t", run.trajectory_path, "-c", damaged, "-o", out], capsys)
    assert "Traceback" not in err
    assert code in (0, 1), err
    if code == 1:
        assert len(message_lines(err)) == 1 and message_lines(err)[0].startswith(f"{ERROR_PREFIX}{damaged}: ")
        assert not out.exists()
    else:
        from kinreg.io.e57 import list_e57_scans

        assert sum(h.n_points for h in list_e57_scans(out)) > 0
    assert not list((tmp_path / "out").glob(".*.tmp-*"))


# --------------------------------------------------------------------------- interrupted runs


def test_interrupted_slice_leaves_no_file_that_looks_finished(
    tmp_path: Path, base_run: SyntheticRun, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    original = e57_writer._write_packets
    calls: list[int] = []

    def write_then_interrupt(*args: Any) -> None:
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        original(*args)

    monkeypatch.setattr(e57_writer, "_write_packets", write_then_interrupt)
    out = tmp_path / "out" / "seq.e57"
    code, _, err = run_cli(["slice", "-t", base_run.trajectory_path, "-c", base_run.cloud_path, "-o", out], capsys)
    assert code == 130
    assert message_lines(err) == ["kinreg: interrupted"]
    assert files_under(tmp_path / "out") == []


def test_interrupted_process_leaves_no_file_that_looks_finished(
    tmp_path: Path, base_run: SyntheticRun, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ctrl-C while the corrected cloud is being written: no corrected.laz, no temporary file,
    and none of the files that mark a finished run (stations.csv, report.json)."""
    from kinreg.run import corrected_cloud

    original = corrected_cloud._write_points  # laspy's LasWriter.write_points, with the header's statistics

    def interrupt(*args: object) -> None:
        original(*args)
        raise KeyboardInterrupt

    monkeypatch.setattr(corrected_cloud, "_write_points", interrupt)
    out = tmp_path / "out"
    code, _, err = run_cli(["process", "-t", base_run.trajectory_path, "-c", base_run.cloud_path, "-o", out,
                            "--window-s", "4"], capsys)
    assert code == 130, err
    assert message_lines(err) == ["kinreg: interrupted"]
    names = {p.name for p in files_under(out)}
    assert not names & {"corrected.laz", "stations.csv", "report.json", "report.html", "links.csv", "sequence.e57"}
    assert not [n for n in names if ".tmp-" in n]


def test_usage_errors_are_usage_errors_not_internal_errors(capsys: pytest.CaptureFixture[str]) -> None:
    # typer >= 0.2x raises its own copy of click's exceptions; they used to end as "internal error".
    code, _, err = run_cli(["slice", "--bogus"], capsys)
    assert code == 2 and "No such option: --bogus" in err and "internal error" not in err
    code, _, err = run_cli(["slice", "-t", "x.txt"], capsys)
    assert code == 2 and "Missing option" in err and "internal error" not in err


def test_disconnected_parts_can_each_be_adjusted_in_their_own_datum(
    tmp_path: Path, base_run: SyntheticRun, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import json

    env = Env(tmp_path, base_run, monkeypatch)
    case = disconnected_network(env)
    config = env.tmp / "fix_each.toml"
    config.write_text('[block]\ndisconnected = "fix_each"\n')
    out = env.tmp / "fix_each_out"
    args = [str(a) for a in case.args]
    args[args.index("-o") + 1] = str(out)
    with pytest.raises(SystemExit) as info:
        main([*args, "--config", str(config)])
    assert info.value.code == 0, capsys.readouterr().err
    report = json.loads((out / "report.json").read_text())
    assert "disconnected part(s) each on its first station" in report["adjustment"]["datum"]


def test_a_block_that_cannot_converge_is_exit_1_with_no_outputs_or_a_report_marked_failed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import json

    sample = Path(__file__).parent.parent / "sample_data"
    out = tmp_path / "out"
    args = ["process", "-t", sample / "run_trajectory.txt", "-c", sample / "run_cloud.laz", "-o", out]
    code, _, err = run_cli(args, capsys)
    assert code == 0, err
    assert (out / "corrected.laz").exists() and (out / "report.json").exists()
    # Resumed with one iteration, too few to bring the stations from the trajectory's poses to
    # the solution: one line, exit 1, and the earlier run's outputs are gone too.
    one = tmp_path / "one_iteration.toml"
    one.write_text("[block]\nmax_iterations = 1\n")
    code, _, err = run_cli([*args, "--config", one, "--resume"], capsys)
    lines = message_lines(err)
    assert code == 1 and "Traceback" not in err
    assert len(lines) == 1, err
    assert re.search(r"the block adjustment failed: no convergence after 1 iterations \(sigma0 .*\); nothing "
                     r"was written", lines[0]), lines[0]
    assert result_files(out) == []
    # With on_failure = "report": exit 1 still, and only a report marked failed.
    report_toml = tmp_path / "report.toml"
    report_toml.write_text('[block]\nmax_iterations = 1\non_failure = "report"\n')
    code, _, err = run_cli([*args, "--config", report_toml, "--resume"], capsys)
    lines = message_lines(err)
    assert code == 1
    assert len(lines) == 1 and "report.html in" in lines[0] and "marked failed" in lines[0], err
    assert sorted(p.name for p in result_files(out)) == ["links.csv", "planes.csv", "report.html", "report.json"]
    report = json.loads((out / "report.json").read_text())
    assert report["adjustment"]["status"] == "failed"
    assert report["adjustment"]["global_test_passed"] is False
    assert report["adjustment"]["failure"] == "no convergence after 1 iterations"
    assert "ADJUSTMENT FAILED" in (out / "report.html").read_text()


def test_a_network_whose_links_all_fail_is_exit_1_never_a_result_of_sigma_zero(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # No pair of scans shares enough planes to link (as where every link fails its test): the
    # block would be the trajectory alone, its redundancy 0 and every sigma 0.0 mm.
    sample = Path(__file__).parent.parent / "sample_data"
    config = tmp_path / "no_links.toml"
    config.write_text("[matching]\nmin_matches = 60\n")
    out = tmp_path / "out"
    args = ["process", "-t", sample / "run_trajectory.txt", "-c", sample / "run_cloud.laz", "-o", out,
            "--config", config]
    code, _, err = run_cli(args, capsys)
    lines = message_lines(err)
    assert code == 1 and "Traceback" not in err
    assert len(lines) == 1, err
    assert "no plane link and no control point is left to check the trajectory" in lines[0], lines[0]
    assert result_files(out) == []
    # With on_failure = "report": the failure on the report's first line, the link graph, links.csv
    # and planes.csv to see why, and no result.
    config.write_text('[matching]\nmin_matches = 60\n[block]\non_failure = "report"\n')
    code, _, err = run_cli([*args, "--resume"], capsys)
    assert code == 1 and "Traceback" not in err, err
    assert sorted(p.name for p in result_files(out)) == ["links.csv", "planes.csv", "report.html", "report.json"]
    html = (out / "report.html").read_text()
    assert html.index("ADJUSTMENT FAILED: no plane link") < html.index("<h2")
    assert "Link graph" in html and "0.0 mm" not in html
    report = json.loads((out / "report.json").read_text())
    assert report["adjustment"]["status"] == "failed" and len(report["stations"]["rows"]) > 10
