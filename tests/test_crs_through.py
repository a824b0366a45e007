"""The CRS and the header travel through: corrected.laz keeps VLRs, EVLRs, point format, scales and
header fields; report.json names the CRS; sequence.e57 carries it as coordinateMetadata; a run at
UTM-sized coordinates gives the stations of the unshifted run."""

from __future__ import annotations

import csv
import datetime
import json
import uuid
from pathlib import Path

import laspy
import numpy as np
import pytest
from laspy.vlrs.vlrlist import VLRList
from pye57 import libe57

from kinreg.geometry import Pose
from kinreg.io.e57_writer import write_e57_sequence
from kinreg.io.las import read_las_crs
from kinreg.run.corrected_cloud import write_corrected_las
from kinreg.types import Scan, ScanKind

SAMPLE = Path(__file__).resolve().parents[1] / "sample_data"
UTM = np.array([500_000.0, 5_400_000.0, 0.0])
WKT = ('PROJCS["WGS 84 / UTM zone 32N",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563,'
       'AUTHORITY["EPSG","7030"]],AUTHORITY["EPSG","6326"]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433],'
       'AUTHORITY["EPSG","4326"]],PROJECTION["Transverse_Mercator"],PARAMETER["latitude_of_origin",0],'
       'PARAMETER["central_meridian",9],PARAMETER["scale_factor",0.9996],PARAMETER["false_easting",500000],'
       'PARAMETER["false_northing",0],UNIT["metre",1,AUTHORITY["EPSG","9001"]],AXIS["Easting",EAST],'
       'AXIS["Northing",NORTH],AUTHORITY["EPSG","32632"]]')


class Shift:
    """A stand-in for DriftCorrection: every point moves by ``delta``."""

    def __init__(self, delta: np.ndarray) -> None:
        self.delta = delta

    def apply_to_points(self, xyz: np.ndarray, stamps_s: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        if out is None:
            return xyz + self.delta
        np.add(xyz.T, self.delta[:, None], out=out)
        return out.T


def georeferenced_las(path: Path, n: int = 5000) -> laspy.LasHeader:
    """A LAS 1.4 point format 6 file at UTM coordinates with a WKT VLR, an EVLR and set header fields."""
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.array([500_010.0, 5_400_020.0, 100.0])
    header.system_identifier = "kinreg test scanner"
    header.generating_software = "hand made"
    header.creation_date = datetime.date(2024, 3, 5)
    header.uuid = uuid.UUID("12345678-1234-5678-1234-567812345678")
    header.file_source_id = 77
    header.global_encoding.wkt = True
    header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(WKT))
    header.vlrs.append(laspy.VLR(user_id="kinreg_test", record_id=7, description="a VLR", record_data=b"\x01\x02"))
    rng = np.random.default_rng(0)
    las = laspy.LasData(header)
    las.x = 500_010.0 + rng.random(n) * 20
    las.y = 5_400_020.0 + rng.random(n) * 10
    las.z = 100.0 + rng.random(n) * 3
    las.gps_time = 1000.0 + np.arange(n) * 0.01
    las.intensity = rng.integers(0, 65535, n, dtype=np.uint16)
    las.classification = rng.integers(0, 10, n, dtype=np.uint8)
    las.evlrs = VLRList([laspy.VLR(user_id="kinreg_test", record_id=9, description="an EVLR",
                                         record_data=b"extended" * 100)])
    las.write(str(path))
    return las.header


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_corrected_cloud_keeps_header_vlrs_and_evlrs(tmp_path, suffix):
    source = tmp_path / f"in{suffix}"
    georeferenced_las(source)
    target = tmp_path / f"out{suffix}"
    n = write_corrected_las(source, target, Shift(np.array([0.010, -0.002, 0.0])), chunk_points=1200)  # type: ignore[arg-type]
    assert n == 5000
    src, out = laspy.read(str(source)), laspy.read(str(target))
    for field in ("version", "system_identifier", "generating_software", "creation_date", "uuid", "file_source_id",
                  "point_count"):
        assert getattr(out.header, field) == getattr(src.header, field), field
    assert out.header.point_format.id == 6
    assert out.header.global_encoding.wkt
    assert np.array_equal(out.header.scales, src.header.scales)
    assert np.array_equal(out.header.offsets, src.header.offsets)
    vlrs = [(v.user_id, v.record_id) for v in out.header.vlrs if v.user_id != "laszip encoded"]
    # the input's VLRs, then the extra-bytes record of the per-point sigma and correction length
    assert vlrs == [("LASF_Projection", 2112), ("kinreg_test", 7), ("LASF_Spec", 4)]
    assert [(e.user_id, e.record_id, bytes(e.record_data)) for e in out.evlrs] == \
        [("kinreg_test", 9, b"extended" * 100)]
    assert read_las_crs(target).wkt == WKT
    # Only X, Y, Z change, by the correction (integer units of 1 mm).
    assert np.array_equal(np.asarray(out.X) - np.asarray(src.X), np.full(5000, 10))
    assert np.array_equal(np.asarray(out.Y) - np.asarray(src.Y), np.full(5000, -2))
    for field in ("Z", "gps_time", "intensity", "classification"):
        assert np.array_equal(np.asarray(out[field]), np.asarray(src[field])), field


def test_sequence_e57_carries_the_crs(tmp_path):
    scan = Scan(0, "qs_00000", ScanKind.QUASI_STATIC, Pose(np.array([1.0, 0, 0, 0]), UTM + [1.0, 2.0, 3.0]),
                np.random.default_rng(1).random((100, 3)), stamps_s=np.linspace(0, 1, 100), t_s=0.5, t_start_s=0.0,
                t_end_s=1.0)
    path = tmp_path / "sequence.e57"
    write_e57_sequence(path, [scan], coordinate_metadata=WKT)
    imf = libe57.ImageFile(str(path), "r")
    try:
        assert libe57.StringNode(imf.root().get("coordinateMetadata")).value() == WKT
    finally:
        imf.close()


def _cut_sample(folder: Path, shift: np.ndarray, wkt: str, seconds: float = 75.0) -> tuple[Path, Path]:
    """The first ``seconds`` of the sample run, moved by ``shift`` (offsets too), with ``wkt``."""
    folder.mkdir()
    las = laspy.read(str(SAMPLE / "run_cloud.laz"))
    t0 = float(np.min(las.gps_time))
    keep = np.asarray(las.gps_time) < t0 + seconds
    header = laspy.LasHeader(version=las.header.version, point_format=las.header.point_format)
    header.scales = las.header.scales
    header.offsets = las.header.offsets + shift
    if wkt:
        header.global_encoding.wkt = True
        header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(wkt))
    out = laspy.LasData(header)
    # The same integer coordinates with the offsets moved: every point moves by exactly ``shift``.
    out.points = laspy.ScaleAwarePointRecord(las.points.array[keep].copy(), header.point_format, header.scales,
                                             header.offsets)
    cloud = folder / "cloud.laz"
    out.write(str(cloud))
    rows = []
    with open(SAMPLE / "run_trajectory.txt") as f:
        for line in f:
            if line.startswith("%"):
                rows.append(line.rstrip("\n"))
                continue
            v = line.split()
            if float(v[0]) > t0 + seconds + 1.0:
                break
            xyz = [float(v[k]) + shift[k - 1] for k in (1, 2, 3)]
            rows.append(" ".join([v[0], *(f"{c:.6f}" for c in xyz), *v[4:]]))
    trajectory = folder / "trajectory.txt"
    trajectory.write_text("\n".join(rows) + "\n")
    return trajectory, cloud


def _stations(path: Path) -> dict[str, np.ndarray]:
    with open(path) as f:
        return {r["station"]: np.array([float(r["x"]), float(r["y"]), float(r["z"])]) for r in csv.DictReader(f)}


@pytest.mark.slow
def test_utm_run_with_wkt_agrees_with_the_unshifted_run(tmp_path):
    from kinreg.config import load_config
    from kinreg.run.pipeline import ProcessInputs, process

    config = load_config()
    results = {}
    for name, shift, wkt in (("local", np.zeros(3), ""), ("utm", UTM, WKT)):
        trajectory, cloud = _cut_sample(tmp_path / f"in_{name}", shift, wkt)
        out = tmp_path / f"out_{name}"
        process(ProcessInputs(trajectory, cloud), out, config)
        results[name] = out
    local, utm = _stations(results["local"] / "stations.csv"), _stations(results["utm"] / "stations.csv")
    assert local.keys() == utm.keys() and len(local) >= 8
    worst = max(np.max(np.abs(utm[k] - UTM - local[k])) for k in local)
    assert worst < 1e-4  # < 0.1 mm
    report = json.loads((results["utm"] / "report.json").read_text())
    assert report["crs"]["epsg"] == 32632
    assert "UTM zone 32N" in report["crs"]["name"]
    assert json.loads((results["local"] / "report.json").read_text())["crs"] == {}
    assert read_las_crs(results["utm"] / "corrected.laz").wkt == WKT
    imf = libe57.ImageFile(str(results["utm"] / "sequence.e57"), "r")
    try:
        assert libe57.StringNode(imf.root().get("coordinateMetadata")).value() == WKT
    finally:
        imf.close()
    html = (results["utm"] / "report.html").read_text()
    assert "UTM zone 32N (EPSG:32632)" in html
