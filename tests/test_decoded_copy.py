"""Slicing keeps a LAZ cloud's decoded point records in the spill, and the corrected cloud is
written from them instead of decoding the LAZ again: the same bytes either way."""

from __future__ import annotations

import errno
from pathlib import Path

import laspy
import numpy as np
import pytest
from conftest import random_correction, write_synthetic_run

from kinreg.config import KinregConfig, SlicingConfig, load_config
from kinreg.errors import CloudError, OutputError
from kinreg.io.cloud import TimeFilter, open_cloud
from kinreg.run import spill
from kinreg.run.corrected_cloud import read_record_chunks, write_corrected_las
from kinreg.run.spill import RECORDS_FILE, adopt_records, make_spill_folder, slice_quasi_static


def write_busy_cloud(folder: Path, point_format: int = 7):
    """A synthetic run whose cloud has every field of its point format filled (colours,
    classification, flags, scan angle, source id), so that a copy of only some layers shows."""
    run = write_synthetic_run(folder, n_points=40_000, point_format=point_format)
    las = laspy.read(run.cloud_path)
    rng = np.random.default_rng(11)
    n = len(las.points)
    las.classification = rng.integers(0, 20, n, dtype=np.uint8)
    las.user_data = rng.integers(0, 255, n, dtype=np.uint8)
    las.point_source_id = rng.integers(0, 65535, n, dtype=np.uint16)
    las.scan_angle = rng.integers(-9000, 9000, n, dtype=np.int16)
    las.return_number = rng.integers(1, 4, n, dtype=np.uint8)
    las.number_of_returns = np.full(n, 4, dtype=np.uint8)
    if "red" in las.point_format.dimension_names:
        for name in ("red", "green", "blue"):
            setattr(las, name, rng.integers(0, 65535, n, dtype=np.uint16))
    las.write(run.cloud_path)
    return run


def slice_keeping(run, folder: Path, time_offset_s: float = 0.0, chunk_points: int = 7_000):
    with open_cloud(run.cloud_path, times=TimeFilter(time_offset_s)) as cloud:
        return slice_quasi_static(run.trajectory, cloud, SlicingConfig(window_s=5.0, min_points=100), chunk_points,
                                  workdir=folder, keep_records=True)


def test_the_copy_holds_every_field_as_stored_before_the_time_offset(tmp_path: Path) -> None:
    run = write_busy_cloud(tmp_path / "run")
    stored = laspy.read(run.cloud_path).points.array
    # a time offset shifts the times the slicing sees, never the copy's (the corrected cloud keeps them)
    with slice_keeping(run, tmp_path, time_offset_s=1e-3) as sequence:
        assert sequence.records is not None and sequence.records.name == RECORDS_FILE
        copy = np.fromfile(sequence.records, dtype=stored.dtype)
        assert copy.tobytes() == stored.tobytes()
        scan = sequence.read_scan(0)
        assert scan.stamps_s.min() >= stored["gps_time"].min() + 0.9e-3  # the scans' times are shifted


def test_the_corrected_cloud_from_the_copy_is_the_one_decoded_again(tmp_path: Path) -> None:
    run = write_busy_cloud(tmp_path / "run")
    correction, _, _ = random_correction(run.trajectory, 6, np.random.default_rng(2), 0.003, 0.03, margin_s=1.0)
    with slice_keeping(run, tmp_path) as sequence:
        from_copy = write_corrected_las(run.cloud_path, tmp_path / "copy.laz", correction, chunk_points=9_000,
                                        records=sequence.records)
    decoded = write_corrected_las(run.cloud_path, tmp_path / "decoded.laz", correction, chunk_points=9_000)
    assert from_copy == decoded == 40_000
    assert (tmp_path / "copy.laz").read_bytes() == (tmp_path / "decoded.laz").read_bytes()


def test_no_copy_of_an_uncompressed_cloud_or_without_room(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    plain = write_synthetic_run(tmp_path / "plain", laz=False)
    with slice_keeping(plain, tmp_path) as sequence:
        assert sequence.records is None  # reading a LAS is as cheap as reading a copy
    run = write_synthetic_run(tmp_path / "run")
    monkeypatch.setattr(spill.shutil, "disk_usage", lambda path: type("Usage", (), {"free": 10 << 20})())
    with slice_keeping(run, tmp_path) as sequence:
        assert sequence.records is None
        assert len(sequence) > 0  # sliced all the same


def test_a_copy_of_another_size_is_refused_naming_it(tmp_path: Path) -> None:
    run = write_synthetic_run(tmp_path / "run")
    header = laspy.open(run.cloud_path).header
    with slice_keeping(run, tmp_path) as sequence:
        records = sequence.records
        with open(records, "r+b") as f:
            f.truncate(records.stat().st_size - header.point_format.size)
        with pytest.raises(CloudError, match=f"{RECORDS_FILE}.*not 60,000 points"):
            next(read_record_chunks(records, header.point_format, header.scales, header.offsets,
                                    header.point_count, 1000))


def test_a_failed_write_of_the_copy_is_the_spills_one_line_error(tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    run = write_synthetic_run(tmp_path / "run")

    class Full:
        name = str(tmp_path / "never")

        def write(self, data: object) -> int:
            raise OSError(errno.ENOSPC, "No space left on device")

        def close(self) -> None:
            pass

        def __enter__(self) -> Full:
            return self

        def __exit__(self, *exc: object) -> None:
            pass

    monkeypatch.setattr(spill, "_records_file", lambda cloud, folder: Full())
    with pytest.raises(OutputError, match="No space left|disk"):
        slice_keeping(run, tmp_path)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(spill.SPILL_PREFIX)]  # nothing left behind


def test_process_writes_the_same_corrected_cloud_with_and_without_the_copy(tmp_path: Path,
                                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    from kinreg.run import corrected_cloud
    from kinreg.run.pipeline import ProcessInputs, process
    from kinreg.simulation.files import write_run
    from kinreg.simulation.run import SimulationConfig, simulate_run

    write_run(simulate_run(SimulationConfig(seed=5, duration_s=24.0)), tmp_path / "data")
    inputs = ProcessInputs(tmp_path / "data" / "run_trajectory.txt", tmp_path / "data" / "run_cloud.laz")
    read = []
    real = corrected_cloud.read_record_chunks
    monkeypatch.setattr(corrected_cloud, "read_record_chunks", lambda *a, **k: read.append(a[0]) or real(*a, **k))
    (tmp_path / "off.toml").write_text("[slicing]\nkeep_decoded = false\n")
    process(inputs, tmp_path / "off", load_config(tmp_path / "off.toml"))
    assert not read
    process(inputs, tmp_path / "on", KinregConfig())
    assert len(read) == 1 and read[0].name == RECORDS_FILE
    for name in ("corrected.laz", "sequence.e57", "stations.csv", "trajectory_corrected.txt"):
        assert (tmp_path / "on" / name).read_bytes() == (tmp_path / "off" / name).read_bytes(), name


def test_slicing_again_reads_the_first_slicings_copy_and_links_it(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    from kinreg.io.las import LasCloudReader

    run = write_busy_cloud(tmp_path / "run")
    config = SlicingConfig(window_s=2.5, min_points=100)
    with open_cloud(run.cloud_path) as cloud:
        expected = slice_quasi_static(run.trajectory, cloud, config, 7_000, workdir=tmp_path)
    with slice_keeping(run, tmp_path) as first:
        monkeypatch.setattr(LasCloudReader, "_decoded_arrays", lambda *a, **k: pytest.fail("decoded again"))
        folder = make_spill_folder(config, tmp_path)
        copy = adopt_records(first.records, folder)
        assert copy is not None and copy.stat().st_ino == first.records.stat().st_ino  # linked, not copied
        with open_cloud(run.cloud_path, decoded=copy) as cloud, \
                slice_quasi_static(run.trajectory, cloud, config, 7_000, folder=folder, keep_records=True) as again:
            assert again.records == copy
            assert again.summary == expected.summary and len(again) == len(expected) > len(first)
            for i in range(len(again)):
                a, b = again.read_scan(i), expected.read_scan(i)
                assert np.array_equal(a.points_xyz, b.points_xyz) and np.array_equal(a.stamps_s, b.stamps_s)
    expected.close()


def test_process_sliced_again_decodes_the_cloud_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from kinreg.io.las import LasCloudReader
    from kinreg.run.pipeline import ProcessInputs, process
    from kinreg.simulation.files import write_run
    from kinreg.simulation.run import SimulationConfig, simulate_run

    write_run(simulate_run(SimulationConfig(seed=5, duration_s=24.0)), tmp_path / "data")
    inputs = ProcessInputs(tmp_path / "data" / "run_trajectory.txt", tmp_path / "data" / "run_cloud.laz")
    decodes = []
    real = LasCloudReader._decoded_arrays
    monkeypatch.setattr(LasCloudReader, "_decoded_arrays",
                        lambda self, *a, **k: decodes.append(1) or real(self, *a, **k))
    # any smear: sliced again with 3 s windows
    again = "[slicing]\nmax_smear_share = 1e-9\nshown_smear_share = 1e-9\nmin_window_s = 3.0\n"
    (tmp_path / "off.toml").write_text(again + "keep_decoded = false\n")
    (tmp_path / "on.toml").write_text(again)
    off = process(inputs, tmp_path / "off", load_config(tmp_path / "off.toml"))
    assert len(decodes) == 2  # each slicing (and the corrected cloud through laspy's own reader)
    decodes.clear()
    process(inputs, tmp_path / "on", load_config(tmp_path / "on.toml"))
    assert len(decodes) == 1
    assert off.n_stations == 8  # 3 s windows
    for name in ("corrected.laz", "sequence.e57", "stations.csv", "trajectory_corrected.txt"):
        assert (tmp_path / "on" / name).read_bytes() == (tmp_path / "off" / name).read_bytes(), name
