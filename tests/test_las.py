import laspy
import numpy as np
import pytest
from conftest import write_synthetic_run

from kinreg.errors import CloudError
from kinreg.io.cloud import open_cloud


@pytest.mark.realdata
def test_real_laz_time_sorted(realdata):
    with open_cloud(realdata / "autzen_trim.laz") as reader:
        assert reader.info.n_points == 110_000 and reader.info.has_time
        chunks = list(reader.iter_chunks(25_000))
    assert [len(c) for c in chunks] == [25_000] * 4 + [10_000]
    t = np.concatenate([c.stamps_s for c in chunks])
    assert t.dtype == np.float64 and np.all(np.diff(t) >= 0)
    assert t[-1] - t[0] == pytest.approx(6.5, abs=0.1)
    assert chunks[-1].first_index == 100_000
    xyz = np.concatenate([c.xyz for c in chunks])
    assert xyz.dtype == np.float64
    las = laspy.read(realdata / "autzen_trim.laz")
    np.testing.assert_array_equal(xyz[:, 0], np.asarray(las.x))


@pytest.mark.realdata
def test_real_las_not_time_sorted(realdata):
    with open_cloud(realdata / "vegetation_1_3.las") as reader:
        t = np.concatenate([c.stamps_s for c in reader.iter_chunks(1000)])
    assert len(t) == 10_683
    assert np.any(np.diff(t) < 0)


def test_chunking_does_not_change_points(tmp_path):
    # More points than one LAZ chunk (50,000), so the parallel decoder handles several at once.
    run = write_synthetic_run(tmp_path, n_points=160_000)
    with open_cloud(run.cloud_path) as reader:
        a = np.concatenate([c.xyz for c in reader.iter_chunks(3_001)])
        b = np.concatenate([c.xyz for c in reader.iter_chunks(2_000_000)])
        t = np.concatenate([c.stamps_s for c in reader.iter_chunks(2_000_000)])
        intensity = np.concatenate([c.intensity for c in reader.iter_chunks(2_000_000)])
    np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(b, run.xyz, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(t, run.stamps_s)
    las = laspy.read(run.cloud_path)
    np.testing.assert_array_equal(intensity, np.asarray(las.intensity, dtype=np.float32))


def test_missing_gps_time_is_a_clear_error(tmp_path):
    run = write_synthetic_run(tmp_path, n_points=100, point_format=0, laz=False)
    with pytest.raises(CloudError, match="no gps_time field") as info:
        open_cloud(run.cloud_path)
    assert str(run.cloud_path) in str(info.value)
    with open_cloud(run.cloud_path, require_time=False) as reader:
        assert next(iter(reader.iter_chunks())).stamps_s is None


def test_truncated_laz_is_a_clear_error(tmp_path):
    run = write_synthetic_run(tmp_path, n_points=200_000)
    data = run.cloud_path.read_bytes()
    cut = tmp_path / "cut.laz"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(CloudError, match="cut.laz"), open_cloud(cut) as reader:
        for _ in reader.iter_chunks(50_000):
            pass


def test_not_a_cloud(tmp_path):
    bad = tmp_path / "bad.laz"
    bad.write_bytes(b"this is not a LAS file at all" * 10)
    with pytest.raises(CloudError, match="cannot open as LAS/LAZ"):
        open_cloud(bad)
    empty = tmp_path / "empty.las"
    empty.write_bytes(b"")
    with pytest.raises(CloudError, match="empty.las"):
        open_cloud(empty)
    xyz = tmp_path / "x.xyz"
    xyz.write_text("1 2 3")
    with pytest.raises(CloudError, match="unsupported point cloud format"):
        open_cloud(xyz)
