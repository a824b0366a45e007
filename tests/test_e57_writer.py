"""kinreg's own E57 writer (numpy, no libE57) against libE57's: the same content, as libE57 and the
independent Rust reader read it; every page's CRC-32C checks."""

from __future__ import annotations

import re
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from crc32c import crc32c
from e57fixtures import write_libe57_sequence
from pye57 import libe57

from kinreg.geometry import Pose, rotvec_to_quat
from kinreg.io import e57_writer
from kinreg.io.e57_writer import LIBRARY_VERSION, write_e57_sequence
from kinreg.types import Scan, ScanKind

T0 = 1623220971.15523
UTM = np.array([500000.123, 5400000.456, 300.789])
CRS = 'PROJCS["ETRS89 / UTM zone 32N (Straße)",GEOGCS["x"]]> & <y>",UNIT["metre",1]]'
BLOCK = 5_000


def _scans() -> list[Scan]:
    rng = np.random.default_rng(1857)

    def scan(k: int, n: int, *, intensity: bool = True, times: bool = True, window: bool = True,
             utm: bool = False, name: str = "") -> Scan:
        t_start = T0 + 5.0 * k
        t = UTM + rng.normal(0.0, 20.0, 3)
        t[2] = -0.0 if k == 1 else t[2]  # a zero is left out of the XML: read back as +0.0 by both
        xyz = rng.normal(0.0, 10.0, (n, 3)) + (UTM if utm else 0.0)
        values = rng.uniform(0.0, 4000.0, n).astype(np.float32)
        if utm and n:
            values[n // 2] = 0.0  # intensityMinimum 0: its own formatting
        return Scan(
            scan_id=k, name=name or f"qs_{k:05d}", kind=ScanKind.QUASI_STATIC,
            T_obj_scan=Pose(rotvec_to_quat(rng.normal(0.0, 1.0, 3)), t), points_xyz=xyz,
            stamps_s=np.sort(t_start + rng.uniform(0.0, 5.0, n)) if times else None,
            intensity=values if intensity else None,
            t_s=t_start + 2.5 if window else float("nan"),
            t_start_s=t_start if window else float("nan"),
            t_end_s=t_start + 5.0 if window else float("nan"),
        )

    return [
        scan(0, 3 * BLOCK + 1234),  # several blocks, the last one short
        scan(1, 700, intensity=False),
        scan(2, 50, times=False, window=False),  # no times at all: no acquisition times
        scan(3, 0),  # empty
        scan(4, 4321, utm=True, window=False, name="Straße ]]> <&> qs_4"),
        scan(5, 9, times=False, intensity=False),
    ]


def _node(node: Any, path: str, values: dict[str, Any], arrays: dict[str, dict[str, np.ndarray]]) -> None:
    """Every node under ``node`` by its path: type and value (floats as their bits), and every
    compressed vector's fields read in full."""
    # pye57 hands out nodes as their own classes, or as Node to be cast by type().
    types = {libe57.E57_STRUCTURE: libe57.StructureNode, libe57.E57_VECTOR: libe57.VectorNode,
             libe57.E57_COMPRESSED_VECTOR: libe57.CompressedVectorNode, libe57.E57_INTEGER: libe57.IntegerNode,
             libe57.E57_FLOAT: libe57.FloatNode, libe57.E57_STRING: libe57.StringNode}
    if type(node) is libe57.Node:
        node = types[node.type()](node)
    if isinstance(node, libe57.StructureNode):
        children = [node.get(i) for i in range(node.childCount())]
        values[path] = ("Structure", [c.elementName() for c in children])
        for c in children:
            _node(c, f"{path}/{c.elementName()}", values, arrays)
    elif isinstance(node, libe57.VectorNode):
        values[path] = ("Vector", node.childCount(), node.allowHeteroChildren())
        for i in range(node.childCount()):
            _node(node.get(i), f"{path}/{i}", values, arrays)
    elif isinstance(node, libe57.CompressedVectorNode):
        values[path] = ("CompressedVector", node.childCount())
        _node(node.prototype(), f"{path}/prototype", values, arrays)
        _node(node.codecs(), f"{path}/codecs", values, arrays)
        arrays[path] = _read_points(node)
    elif isinstance(node, libe57.IntegerNode):
        values[path] = ("Integer", node.value(), node.minimum(), node.maximum())
    elif isinstance(node, libe57.FloatNode):
        values[path] = ("Float", node.precision(),
                        *(struct.pack("<d", x) for x in (node.value(), node.minimum(), node.maximum())))
    elif isinstance(node, libe57.StringNode):
        values[path] = ("String", node.value())
    else:
        raise AssertionError(f"{path}: unexpected node {node!r}")


def _read_points(cv: Any) -> dict[str, np.ndarray]:
    n = cv.childCount()
    if n == 0:
        return {}  # libE57 takes no buffer of size 0
    prototype = libe57.StructureNode(cv.prototype())
    imf = cv.destImageFile()
    columns: dict[str, np.ndarray] = {}
    buffers = libe57.VectorSourceDestBuffer()
    for i in range(prototype.childCount()):
        field = prototype.get(i).elementName()
        single = libe57.FloatNode(prototype.get(i)).precision() == libe57.E57_SINGLE
        columns[field] = np.empty(n, np.float32 if single else np.float64)
        buffers.append(libe57.SourceDestBuffer(imf, field, columns[field], n, False, False))
    reader = cv.reader(buffers)
    assert reader.read() == n
    reader.close()
    return columns


def _content(path: Path) -> tuple[dict[str, Any], dict[str, dict[str, np.ndarray]]]:
    """What libE57 reads, every checksum verified."""
    imf = libe57.ImageFile(str(path), "r", libe57.CHECKSUM_POLICY_ALL)
    try:
        values: dict[str, Any] = {}
        arrays: dict[str, dict[str, np.ndarray]] = {}
        _node(imf.root(), "", values, arrays)
        assert [imf.extensionsPrefix(i) for i in range(imf.extensionsCount())][-1] == "kinreg"
        return values, arrays
    finally:
        imf.close()


@pytest.fixture
def written(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, Path, list[Scan]]:
    """The same scans, by kinreg's writer (blocks of BLOCK points) and by libE57."""
    monkeypatch.setattr(e57_writer, "WRITE_BLOCK_POINTS", BLOCK)
    scans = _scans()
    (tmp_path / "kinreg").mkdir()
    (tmp_path / "libe57").mkdir()
    ours, theirs = tmp_path / "kinreg" / "sequence.e57", tmp_path / "libe57" / "sequence.e57"
    assert write_e57_sequence(ours, scans, coordinate_metadata=CRS) == len(scans)
    write_libe57_sequence(theirs, scans, coordinate_metadata=CRS, block_points=BLOCK)
    return ours, theirs, scans


def test_same_content_as_libe57(written: tuple[Path, Path, list[Scan]]) -> None:
    ours, theirs, scans = written
    our_values, our_arrays = _content(ours)
    their_values, their_arrays = _content(theirs)
    # The one intended difference: which library wrote the file.
    assert our_values.pop("/e57LibraryVersion") == ("String", LIBRARY_VERSION)
    assert their_values.pop("/e57LibraryVersion")[1].endswith(libe57.E57_LIBRARY_ID)
    assert our_values == their_values  # every header value: pose, bounds, limits, times, names, guids, kinreg:*
    assert our_values["/coordinateMetadata"] == ("String", CRS)
    assert our_values["/data3D/4/name"] == ("String", scans[4].name)
    assert our_values["/data3D/1/pose/translation/z"][2] == struct.pack("<d", 0.0)
    assert "/data3D/2/acquisitionStart" not in our_values
    assert our_arrays.keys() == their_arrays.keys()
    for key, columns in our_arrays.items():
        assert columns.keys() == their_arrays[key].keys()
        for field, values in columns.items():
            assert values.dtype == their_arrays[key][field].dtype
            assert values.tobytes() == their_arrays[key][field].tobytes(), (key, field)  # bit for bit
    # ...and they are the scans' values.
    for k, scan in enumerate(scans):
        columns = our_arrays[f"/data3D/{k}/points"]
        if not len(scan):
            assert columns == {}
            continue
        xyz = np.column_stack([columns[f"cartesian{a}"] for a in "XYZ"])
        np.testing.assert_array_equal(xyz, scan.points_xyz)
        if scan.stamps_s is not None:
            start = scan.t_start_s if np.isfinite(scan.t_start_s) else scan.stamps_s.min()
            np.testing.assert_array_equal(columns["timeStamp"], scan.stamps_s - start)
        assert ("intensity" in columns) == (scan.intensity is not None)


def test_same_xml_text_as_libe57(written: tuple[Path, Path, list[Scan]]) -> None:
    """Formatted as libE57 formats it, but for the section offsets and the library's name."""
    e57 = pytest.importorskip("e57")
    ours, theirs, _ = written

    def normal(path: Path) -> str:
        text = re.sub(r'fileOffset="\d+"', 'fileOffset=""', e57.raw_xml(str(path)))
        return re.sub(r"<e57LibraryVersion.*</e57LibraryVersion>", "", text).rstrip()

    assert normal(ours) == normal(theirs)


def test_pages_check_and_damage_is_found(written: tuple[Path, Path, list[Scan]], tmp_path: Path) -> None:
    ours, _, _ = written
    data = ours.read_bytes()
    assert data[:8] == b"ASTM-E57"
    signature, major, minor, length, xml_offset, xml_length, page = struct.unpack("<8sIIQQQQ", data[:48])
    assert (major, minor, length, page) == (1, 0, len(data), 1024)
    assert len(data) % 1024 == 0
    for start in range(0, len(data), 1024):  # the CRC-32C of each page's 1020 bytes, big-endian
        assert data[start + 1020:start + 1024] == crc32c(data[start:start + 1020]).to_bytes(4, "big"), start
    # One changed byte in the points: libE57 (checking every page) refuses to read them.
    damaged = bytearray(data)
    damaged[40_000] ^= 0x01
    bad = tmp_path / "damaged.e57"
    bad.write_bytes(bytes(damaged))
    with pytest.raises(libe57.E57Exception, match="checksum|ErrorBadChecksum"):
        _content(bad)
    # One changed byte in the XML: the file does not open.
    damaged = bytearray(data)
    damaged[xml_offset + 100] ^= 0x01
    bad.write_bytes(bytes(damaged))
    with pytest.raises(libe57.E57Exception):
        _content(bad)


def test_rust_reader_reads_both_alike(written: tuple[Path, Path, list[Scan]]) -> None:
    e57 = pytest.importorskip("e57")
    ours, theirs, scans = written
    our_cloud, their_cloud = e57.read_points(str(ours)), e57.read_points(str(theirs))
    assert our_cloud.points.tobytes() == their_cloud.points.tobytes()
    want = np.concatenate([s.points_in_object_frame() for s in scans])
    assert np.abs(our_cloud.points - want).max() < 1e-6


def test_rerun_gives_identical_bytes(written: tuple[Path, Path, list[Scan]], tmp_path: Path) -> None:
    ours, _, scans = written
    (tmp_path / "again").mkdir()
    write_e57_sequence(tmp_path / "again" / ours.name, scans, coordinate_metadata=CRS)
    assert (tmp_path / "again" / ours.name).read_bytes() == ours.read_bytes()
