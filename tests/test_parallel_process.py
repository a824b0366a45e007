"""The parallel stages give the same result in this process, on local workers and on Dask."""

import pytest

from kinreg.config import KinregConfig
from kinreg.run.pipeline import ProcessInputs, process
from kinreg.simulation.files import write_run
from kinreg.simulation.run import SimulationConfig, simulate_run


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("parallel")
    write_run(simulate_run(SimulationConfig(seed=5, duration_s=36.0)), root / "data")
    return root


def outputs(folder):
    return {name: (folder / name).read_bytes() for name in ("stations.csv", "links.csv", "trajectory_corrected.txt")}


def run(small_run, name, **kwargs):
    data = small_run / "data"
    process(ProcessInputs(data / "run_trajectory.txt", data / "run_cloud.laz"), small_run / name, KinregConfig(),
            **kwargs)
    return outputs(small_run / name)


def test_local_workers_and_dask_cluster_give_identical_results(small_run):
    distributed = pytest.importorskip("distributed")
    serial = run(small_run, "serial", workers=1)
    assert run(small_run, "workers2", workers=2) == serial
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None) as cluster:
        assert run(small_run, "dask", scheduler=cluster.scheduler_address) == serial


def test_sequence_written_on_a_worker_equals_the_one_written_in_this_process(small_run):
    # With local workers sequence.e57 is written on one of them while this process writes
    # corrected.laz; both files must be the same bytes as when written one after the other.
    data = small_run / "data"
    for name, workers in (("overlap-serial", 1), ("overlap-workers2", 2)):
        process(ProcessInputs(data / "run_trajectory.txt", data / "run_cloud.laz"), small_run / name, KinregConfig(),
                workers=workers)
    for name in ("sequence.e57", "corrected.laz", "stations.csv"):
        overlapped = (small_run / "overlap-workers2" / name).read_bytes()
        assert overlapped == (small_run / "overlap-serial" / name).read_bytes(), name
