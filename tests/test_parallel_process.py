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
