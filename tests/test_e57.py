"""E57 reading and writing: round trips through kinreg, pye57 and the independent Rust reader."""

from __future__ import annotations

import errno
import os
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from e57fixtures import write_raw_e57_scan

from kinreg.errors import CloudError, OutputError
from kinreg.geometry import Pose, rotvec_to_quat
from kinreg.io import direct_io
from kinreg.io import e57_writer as kinreg_e57_writer
from kinreg.io.cloud import open_cloud
from kinreg.io.e57 import E57CloudReader, iter_e57_scans, list_e57_scans, read_e57_scan
from kinreg.io.e57_writer import E57SequenceWriter, write_e57_sequence
from kinreg.types import Scan, ScanKind

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
T0 = 1623220971.15523
UTM = np.array([500000.123, 5400000.456, 300.789])
E57_NS = {"e": "http://www.astm.org/COMMIT/E57/2010-e57-v1.0"}

realdata = pytest.mark.skipif(not REALDATA.is_dir(), reason=f"{REALDATA} is absent")


def _scan(
    rng: np.random.Generator, scan_id: int, n: int, intensity: bool = True, window: bool = True
) -> Scan:
    """A quasi-static scan: points up to 50 m in its frame, a rotated pose at UTM coordinates."""
    t_start = T0 + 5.0 * scan_id
    pose = Pose(rotvec_to_quat(rng.normal(0.0, 1.0, 3)), UTM + rng.normal(0.0, 20.0, 3))
    return Scan(
        scan_id=scan_id,
        name=f"qs_{scan_id:05d}",
        kind=ScanKind.QUASI_STATIC,
        T_obj_scan=pose,
        points_xyz=rng.uniform(-50.0, 50.0, (n, 3)),
        stamps_s=np.sort(t_start + rng.uniform(0.0, 5.0, n)),
        intensity=rng.uniform(0.0, 4000.0, n).astype(np.float32) if intensity else None,
        t_s=t_start + 2.5 if window else float("nan"),
        t_start_s=t_start if window else float("nan"),
        t_end_s=t_start + 5.0 if window else float("nan"),
    )


@pytest.fixture
def scans() -> list[Scan]:
    rng = np.random.default_rng(57)
    return [
        _scan(rng, 0, 1500),
        _scan(rng, 1, 700, intensity=False),
        _scan(rng, 2, 9, window=False),  # no window: the time origin is the first point time
        _scan(rng, 3, 0),  # an empty window is still a valid entry
    ]


@pytest.fixture
def sequence(tmp_path: Path, scans: list[Scan]) -> Path:
    path = tmp_path / "sequence.e57"
    assert write_e57_sequence(path, scans) == len(scans)
    return path


def _read_all(reader: E57CloudReader, chunk_points: int) -> tuple[np.ndarray, np.ndarray, list[int]]:
    chunks = list(reader.iter_chunks(chunk_points))
    assert all(0 < len(c) <= chunk_points for c in chunks)
    xyz = np.concatenate([c.xyz for c in chunks])
    stamps = np.concatenate([c.stamps_s for c in chunks if c.stamps_s is not None])
    return xyz, stamps, [c.first_index for c in chunks]


# --------------------------------------------------------------------------- round trips


def test_round_trip_scans_exact(sequence: Path, scans: list[Scan]) -> None:
    read = list(iter_e57_scans(sequence, kind=ScanKind.QUASI_STATIC))
    assert len(read) == len(scans)
    for got, want in zip(read, scans, strict=True):
        assert (got.scan_id, got.name, got.kind) == (want.scan_id, want.name, ScanKind.QUASI_STATIC)
        np.testing.assert_array_equal(got.points_xyz, want.points_xyz)  # double: exact
        assert got.stamps_s is not None
        assert want.stamps_s is not None
        assert got.stamps_s.dtype == np.float64
        np.testing.assert_array_equal(got.stamps_s, want.stamps_s)
        if want.intensity is None:
            assert got.intensity is None
        else:
            np.testing.assert_array_equal(got.intensity, want.intensity)
        np.testing.assert_array_equal(got.T_obj_scan.quat_wxyz, want.T_obj_scan.quat_wxyz)
        np.testing.assert_array_equal(got.T_obj_scan.t_xyz, want.T_obj_scan.t_xyz)
    assert read[0].t_start_s == scans[0].t_start_s
    assert read[0].t_end_s == scans[0].t_end_s
    assert read[0].t_s == scans[0].t_s
    # Without a window the file's acquisition times are the point times' range.
    assert scans[2].stamps_s is not None
    assert read[2].t_start_s == scans[2].stamps_s.min()
    assert read[2].t_end_s == scans[2].stamps_s.max()


def test_read_static_kind_has_nan_times(sequence: Path, scans: list[Scan]) -> None:
    scan = read_e57_scan(sequence, 0)
    assert scan.kind is ScanKind.STATIC
    assert np.isnan(scan.t_s)
    assert np.isnan(scan.t_start_s)
    assert np.isnan(scan.t_end_s)
    np.testing.assert_array_equal(scan.points_xyz, scans[0].points_xyz)
    with pytest.raises(CloudError, match="no scan 9"):
        read_e57_scan(sequence, 9)


def test_headers(sequence: Path, scans: list[Scan], tmp_path: Path) -> None:
    headers = list_e57_scans(sequence)
    assert [h.name for h in headers] == [s.name for s in scans]
    assert [h.n_points for h in headers] == [len(s) for s in scans]
    assert all(h.has_time for h in headers)
    assert headers[0].fields == ("cartesianX", "cartesianY", "cartesianZ", "intensity", "timeStamp")
    assert "intensity" not in headers[1].fields
    assert headers[0].acquisition_start_s == scans[0].t_start_s
    assert headers[0].bounds_min == tuple(scans[0].points_xyz.min(axis=0))
    assert headers[3].bounds_min is None  # an empty scan has no bounds
    assert len({h.guid for h in headers}) == len(headers)
    # Deterministic: the same scans under the same file name give the same bytes.
    again = tmp_path / "again"
    again.mkdir()
    write_e57_sequence(again / sequence.name, scans)
    assert (again / sequence.name).read_bytes() == sequence.read_bytes()


def test_cloud_reader_object_frame(sequence: Path, scans: list[Scan]) -> None:
    with E57CloudReader(sequence) as reader:
        info = reader.info
        xyz, stamps, first = _read_all(reader, 1_000_000)
    want_xyz = np.concatenate([s.points_in_object_frame() for s in scans])
    want_stamps = np.concatenate([s.stamps_s for s in scans if s.stamps_s is not None])
    assert xyz.dtype == np.float64
    assert stamps.dtype == np.float64
    assert np.abs(xyz - want_xyz).max() < 1e-7
    np.testing.assert_array_equal(stamps, want_stamps)
    assert first == [0, 1500, 2200]
    assert (info.format, info.n_points, info.n_scans, info.has_time) == ("E57", 2209, 4, True)
    assert info.bounds_min is not None
    assert info.bounds_max is not None
    assert np.all(want_xyz >= np.array(info.bounds_min) - 1e-6)
    assert np.all(want_xyz <= np.array(info.bounds_max) + 1e-6)
    assert info.time_range_s is not None
    assert info.time_range_s[0] == scans[0].t_start_s


def test_chunked_equals_single_chunk(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Several write blocks per scan as well as several read chunks.
    monkeypatch.setattr(kinreg_e57_writer, "WRITE_BLOCK_POINTS", 4_000)
    rng = np.random.default_rng(3)
    path = tmp_path / "big.e57"
    write_e57_sequence(path, [_scan(rng, 0, 10_001), _scan(rng, 1, 2_345)])
    with open_cloud(path) as reader:
        assert isinstance(reader, E57CloudReader)
        one_xyz, one_t, one_first = _read_all(reader, 100_000)
        many_xyz, many_t, many_first = _read_all(reader, 999)
    np.testing.assert_array_equal(one_xyz, many_xyz)
    np.testing.assert_array_equal(one_t, many_t)
    assert one_first == [0, 10_001]
    assert many_first[:3] == [0, 999, 1998]
    assert 10_001 in many_first


def test_block_and_buffer_sizes_change_no_byte(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The write blocks and paging buffers, kept from block to block and from scan to scan (reused by
    scans of other sizes), and the file buffer's size give the same bytes."""
    scans = [_scan(np.random.default_rng(4), k, n) for k, n in enumerate((10_001, 2_345, 0, 7_000))]
    (tmp_path / "one").mkdir()
    write_e57_sequence(tmp_path / "one" / "sequence.e57", scans)
    monkeypatch.setattr(kinreg_e57_writer, "WRITE_BLOCK_POINTS", 1)  # one packet a block
    monkeypatch.setattr(kinreg_e57_writer, "FILE_BUFFER_BYTES", 3 * 4096)
    (tmp_path / "many").mkdir()
    write_e57_sequence(tmp_path / "many" / "sequence.e57", scans)
    assert (tmp_path / "one" / "sequence.e57").read_bytes() == (tmp_path / "many" / "sequence.e57").read_bytes()


# --------------------------------------------------------------------------- independent readers


def test_pye57_reads_what_kinreg_writes(sequence: Path, scans: list[Scan]) -> None:
    pye57 = pytest.importorskip("pye57")
    e57file = pye57.E57(str(sequence))
    try:
        assert e57file.scan_count == len(scans)
        for i, scan in enumerate(scans[:3]):  # pye57 cannot read an empty scan (buffer of size 0)
            header = e57file.get_header(i)
            np.testing.assert_array_equal(header.rotation, scan.T_obj_scan.quat_wxyz)
            np.testing.assert_array_equal(header.translation, scan.T_obj_scan.t_xyz)
            assert header["name"].value() == scan.name
            assert header.point_count == len(scan)
            # pye57 does not know timeStamp; it only reads the fields it supports.
            data = e57file.read_scan_raw(i, ignore_unsupported_fields=True)
            got = np.column_stack([data["cartesianX"], data["cartesianY"], data["cartesianZ"]])
            np.testing.assert_array_equal(got, scan.points_xyz)
            if scan.intensity is not None:
                np.testing.assert_array_equal(data["intensity"], scan.intensity)
        assert e57file.get_header(0).acquisitionStart_dateTimeValue == scans[0].t_start_s
    finally:
        e57file.close()


def test_rust_e57_reads_what_kinreg_writes(sequence: Path, scans: list[Scan]) -> None:
    e57 = pytest.importorskip("e57")
    cloud = e57.read_points(str(sequence))  # all entries, mapped with their poses
    want = np.concatenate([s.points_in_object_frame() for s in scans])
    assert cloud.points.shape == want.shape
    assert np.abs(cloud.points - want).max() < 1e-7
    # Poses, names and times are not exposed as values; the XML section holds them.
    root = ET.fromstring(e57.raw_xml(str(sequence)))
    entries = root.findall("e:data3D/e:vectorChild", E57_NS)
    assert len(entries) == len(scans)
    for entry, scan in zip(entries, scans, strict=True):
        assert entry.findtext("e:name", namespaces=E57_NS) == scan.name
        quat = [float(entry.findtext(f"e:pose/e:rotation/e:{k}", "0", E57_NS)) for k in "wxyz"]
        t = [float(entry.findtext(f"e:pose/e:translation/e:{k}", "0", E57_NS)) for k in "xyz"]
        np.testing.assert_array_equal(quat, scan.T_obj_scan.quat_wxyz)
        np.testing.assert_array_equal(t, scan.T_obj_scan.t_xyz)
        start = entry.findtext("e:acquisitionStart/e:dateTimeValue", namespaces=E57_NS)
        assert start is not None
        assert scan.stamps_s is not None
        if len(scan):
            assert float(start) == min(scan.t_start_s, scan.stamps_s.min()) or np.isnan(scan.t_start_s)
        assert entry.find("e:points/e:prototype/e:timeStamp", E57_NS) is not None
        assert entry.find("e:points", E57_NS).get("recordCount") == str(len(scan))  # type: ignore[union-attr]


# --------------------------------------------------------------------------- reader failures


def test_require_time(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    scan = _scan(rng, 0, 10)
    untimed = Scan(0, "static_A", ScanKind.STATIC, scan.T_obj_scan, scan.points_xyz)
    path = tmp_path / "static.e57"
    write_e57_sequence(path, [untimed])
    with pytest.raises(CloudError) as info:
        E57CloudReader(path)
    assert str(info.value) == (
        f"{path}: no per-point timeStamp field in scan 0 ('static_A'); kinreg needs point times"
    )
    with E57CloudReader(path, require_time=False) as reader:
        assert not reader.info.has_time
        assert reader.info.time_range_s is None
        (chunk,) = list(reader.iter_chunks())
    assert chunk.stamps_s is None
    assert chunk.intensity is None
    assert np.abs(chunk.xyz - scan.points_in_object_frame()).max() < 1e-7


def test_garbage_truncated_and_corrupted_files(tmp_path: Path, sequence: Path) -> None:
    garbage = tmp_path / "garbage.e57"
    garbage.write_bytes(b"this is not an E57 file\n" * 100)
    with pytest.raises(CloudError, match="not an E57 file"):
        open_cloud(garbage)
    with pytest.raises(CloudError, match="not an E57 file"):
        list_e57_scans(garbage)

    data = sequence.read_bytes()
    truncated = tmp_path / "truncated.e57"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(CloudError, match="truncated"):
        E57CloudReader(truncated)

    # Damage the middle of the first scan's points (bytes 48 to ~54,000): the file opens, and
    # reading fails on that page's checksum.
    corrupted = tmp_path / "corrupted.e57"
    damaged = bytearray(data)
    damaged[30_000:30_060] = bytes(60)
    corrupted.write_bytes(bytes(damaged))
    reader = E57CloudReader(corrupted)  # the header pages are intact
    with pytest.raises(CloudError, match=r"cannot read scan 0 \('qs_00000'\)") as info:
        list(reader.iter_chunks(100))
    reader.close()
    assert str(info.value).startswith(str(corrupted))
    assert "\n" not in str(info.value)

    with pytest.raises(CloudError, match="file not found"):
        list_e57_scans(tmp_path / "missing.e57")


def test_spherical_only_scan_is_converted(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    r = rng.uniform(1.0, 30.0, 50)
    az = rng.uniform(-np.pi, np.pi, 50)
    el = rng.uniform(-1.2, 1.2, 50)
    state = (np.arange(50) % 10 == 0).astype(np.int8)  # every tenth record flagged invalid
    path = tmp_path / "spherical.e57"
    write_raw_e57_scan(path, "tls", {"sphericalRange": r, "sphericalAzimuth": az, "sphericalElevation": el,
                                     "sphericalInvalidState": state})
    scan = read_e57_scan(path, 0, require_pose=False)
    keep = state == 0
    want = np.column_stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)])
    np.testing.assert_allclose(scan.points_xyz, want[keep], atol=1e-12)
    with pytest.raises(CloudError, match="has no pose"):
        read_e57_scan(path, 0)


# --------------------------------------------------------------------------- writer failures


def test_writer_leaves_nothing_on_failure(tmp_path: Path, scans: list[Scan]) -> None:
    bad_points = scans[0].points_xyz.copy()
    bad_points[17, 1] = np.nan
    bad = Scan(9, "bad", ScanKind.QUASI_STATIC, scans[0].T_obj_scan, bad_points)
    with pytest.raises(OutputError, match="non-finite"):
        write_e57_sequence(tmp_path / "a.e57", [scans[0], bad])
    assert list(tmp_path.iterdir()) == []

    def failing():
        yield scans[0]
        yield scans[1]
        raise RuntimeError("slicing failed")

    with pytest.raises(RuntimeError, match="slicing failed"):
        write_e57_sequence(tmp_path / "b.e57", failing())
    assert list(tmp_path.iterdir()) == []

    writer = E57SequenceWriter(tmp_path / "c.e57")
    writer.add_scan(scans[0])
    assert writer.tmp_path.exists()
    writer.abort()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("failing_call", [1, 5, 22])  # of 22 writes
def test_writer_failed_write_leaves_nothing(
    tmp_path: Path, scans: list[Scan], monkeypatch: pytest.MonkeyPatch, failing_call: int
) -> None:
    """A write that fails (here: the disk is full) at the start, mid-scan or at the end becomes an
    OutputError naming the file, and the temporary file is removed."""
    monkeypatch.setattr(kinreg_e57_writer, "FILE_BUFFER_BYTES", 4096)
    original = direct_io._write_all
    calls = []

    def write_then_fail(fd: int, view: memoryview) -> None:
        calls.append(len(view))
        if len(calls) == failing_call:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        original(fd, view)

    monkeypatch.setattr(direct_io, "_write_all", write_then_fail)
    with pytest.raises(OutputError, match="No space left on device") as info:
        write_e57_sequence(tmp_path / "seq.e57", scans)
    assert str(info.value).startswith(str(tmp_path / "seq.e57"))
    assert len(calls) >= failing_call
    assert list(tmp_path.iterdir()) == []


def test_writer_refuses_existing_target(tmp_path: Path, scans: list[Scan]) -> None:
    path = tmp_path / "seq.e57"
    path.write_bytes(b"precious")
    with pytest.raises(OutputError, match="exists; use --overwrite"):
        write_e57_sequence(path, scans)
    assert path.read_bytes() == b"precious"
    assert write_e57_sequence(path, scans[:1], overwrite=True) == 1
    assert [h.name for h in list_e57_scans(path)] == [scans[0].name]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq.e57"]


def test_writer_unwritable_folder(tmp_path: Path, scans: list[Scan]) -> None:
    with pytest.raises(OutputError, match="folder does not exist"):
        E57SequenceWriter(tmp_path / "missing" / "seq.e57")
    if os.geteuid() == 0:
        return  # root writes into read-only folders anyway
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    try:
        with pytest.raises(OutputError, match="cannot create"):
            E57SequenceWriter(locked / "seq.e57")
    finally:
        locked.chmod(0o700)


def test_progress_is_reported(tmp_path: Path, scans: list[Scan]) -> None:
    calls: list[tuple[str, object]] = []

    class Recorder:
        def start(self, stage: str, total: float | None = None, unit: str = "") -> None:
            calls.append(("start", total))

        def advance(self, amount: float = 1.0) -> None:
            calls.append(("advance", amount))

        def finish(self) -> None:
            calls.append(("finish", None))

    write_e57_sequence(tmp_path / "p.e57", scans, progress=Recorder())
    assert calls == [("start", 4), *[("advance", 1)] * 4, ("finish", None)]


# --------------------------------------------------------------------------- real files


@pytest.mark.realdata
@realdata
def test_real_translation_without_rotation() -> None:
    path = REALDATA / "translationWithoutRotation.e57"
    (header,) = list_e57_scans(path)
    assert header.n_points == 4
    assert not header.has_time
    assert header.T_obj_scan is not None
    np.testing.assert_array_equal(header.T_obj_scan.quat_wxyz, [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(header.T_obj_scan.t_xyz, [4.0, 5.0, 6.0])
    scan = read_e57_scan(path, 0)
    with E57CloudReader(path, require_time=False) as reader:
        (chunk,) = list(reader.iter_chunks())
    np.testing.assert_array_equal(chunk.xyz, scan.points_xyz + np.array([4.0, 5.0, 6.0]))
    assert chunk.stamps_s is None


@pytest.mark.realdata
@realdata
def test_real_two_scans_without_pose() -> None:
    path = REALDATA / "pdal_A_B.e57"
    headers = list_e57_scans(path)
    assert [h.n_points for h in headers] == [2, 4]
    assert all(h.T_obj_scan is None for h in headers)  # no pose element at all: identity
    with pytest.raises(CloudError, match=r"scan 0 \('B2 - Cloud'\) has no pose"):
        next(iter_e57_scans(path))
    scans = list(iter_e57_scans(path, require_pose=False))
    assert [len(s) for s in scans] == [2, 4]
    assert all(s.intensity is not None and s.intensity.dtype == np.float32 for s in scans)
    with E57CloudReader(path, require_time=False) as reader:
        assert reader.info.n_points == 6
        assert reader.info.n_scans == 2
        chunks = list(reader.iter_chunks())
    assert [c.first_index for c in chunks] == [0, 2]
    np.testing.assert_array_equal(
        np.concatenate([c.xyz for c in chunks]), np.concatenate([s.points_xyz for s in scans])
    )


@pytest.mark.realdata
@realdata
def test_real_structured_scan_without_time() -> None:
    path = REALDATA / "pumpAVisualReferenceImage.e57"
    with pytest.raises(CloudError, match=r"no per-point timeStamp field in scan 0 \('pumpA'\)"):
        open_cloud(path)
    with E57CloudReader(path, require_time=False) as reader:
        assert reader.info.n_points == 155_201
        assert not reader.info.has_time
        chunks = list(reader.iter_chunks(50_000))
    assert [len(c) for c in chunks] == [50_000, 50_000, 50_000, 5_201]
    xyz = np.concatenate([c.xyz for c in chunks])
    pye57 = pytest.importorskip("pye57")
    e57file = pye57.E57(str(path))
    try:
        data = e57file.read_scan_raw(0, ignore_unsupported_fields=True)
    finally:
        e57file.close()
    np.testing.assert_array_equal(xyz[:, 0], data["cartesianX"])
    np.testing.assert_array_equal(
        np.concatenate([c.intensity for c in chunks if c.intensity is not None]), data["intensity"]
    )
