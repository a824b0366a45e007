"""Executors: the same results, in the same order, in this process, in local worker processes
and on a real Dask cluster (loopback)."""

import ctypes
import importlib.util
import os
import sys
import time

import numpy as np
import pytest
from planefixtures import pose, scan_planes

from kinreg.config import DriftConfig, MatchingConfig, PairwiseConfig
from kinreg.errors import ConfigError
from kinreg.estimate.matching import match_planes
from kinreg.estimate.pairwise import adjust_pair
from kinreg.run.codecs import links_to_arrays
from kinreg.run.executor import THREAD_VARIABLES, ExecutorContext, make_executor, parallel_map

HAVE_DASK = importlib.util.find_spec("distributed") is not None


# Top-level functions: the workers import them by name (see kinreg.run.executor).
def noisy_sum(seed: int) -> np.ndarray:
    """Floating-point work whose result depends only on the item."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(50, 50))
    return np.linalg.solve(a @ a.T + np.eye(50), rng.normal(size=50))


def slow_then_fast(k: int) -> int:
    time.sleep(0.2 if k == 0 else 0.0)  # the first task finishes last
    return k * k


def fail_on_three(k: int) -> int:
    if k == 3:
        raise ValueError("item 3")
    return k


def openblas_threads() -> int | None:
    """The size of the thread pool of the OpenBLAS numpy loaded in this process (None where it
    cannot be read: another BLAS, or no /proc)."""
    try:
        with open("/proc/self/maps") as f:
            paths = sorted({line.split()[-1] for line in f if "openblas" in line.lower() and "/" in line})
    except OSError:
        return None
    for path in paths:
        lib = ctypes.CDLL(path)
        for name in ("scipy_openblas_get_num_threads64_", "openblas_get_num_threads64_", "openblas_get_num_threads"):
            get = getattr(lib, name, None)
            if get is not None:
                get.restype = ctypes.c_int
                return int(get())
    return None


def thread_settings(_: int) -> dict:
    """What a worker runs with: the thread variables and its BLAS pool."""
    np.linalg.svd(np.ones((200, 200)))  # BLAS is loaded and used
    return {"env": {name: os.environ.get(name) for name in THREAD_VARIABLES}, "blas": openblas_threads()}


def link_pair(seed: int) -> dict[str, np.ndarray]:
    """A real stage: two scans' planes matched and adjusted pairwise."""
    rng = np.random.default_rng(seed)
    T_i = pose(rng.normal(0, [0.05, 0.05, 0.3]), [4.0, 3.0, 1.4] + rng.normal(0, 0.3, 3))
    T_j = pose(rng.normal(0, [0.05, 0.05, 0.3]), [7.0, 4.0, 1.5] + rng.normal(0, 0.3, 3))
    planes_i, planes_j = scan_planes(T_i, 0, rng), scan_planes(T_j, 1, rng)
    T_prior = T_i.inverse().compose(T_j)
    matches = match_planes(planes_i, planes_j, T_prior, MatchingConfig())
    link = adjust_pair(0, 1, planes_i, planes_j, T_prior, 6.0, matches, DriftConfig(), PairwiseConfig())
    return links_to_arrays([link])


class Counter:
    def __init__(self) -> None:
        self.n = 0

    def start(self, stage, total=None, unit=""):
        pass

    def advance(self, amount=1.0):
        self.n += amount

    def finish(self):
        pass


def run_all(ctx: ExecutorContext) -> dict:
    progress = Counter()
    seen: dict[int, np.ndarray] = {}
    out = {
        "noisy": parallel_map(noisy_sum, range(20), ctx, progress, on_result=seen.__setitem__),
        "links": parallel_map(link_pair, range(6), ctx),
        "ordered": parallel_map(slow_then_fast, (k for k in range(8)), ctx, max_in_flight=3),
        "map": list(ctx.map(slow_then_fast, range(8), chunksize=2)),
    }
    assert progress.n == 20
    assert sorted(seen) == list(range(20)) and all(seen[k] is out["noisy"][k] for k in seen)
    return out


def assert_identical(a: dict, b: dict) -> None:
    assert a["ordered"] == b["ordered"] == [k * k for k in range(8)]
    assert a["map"] == b["map"] == [k * k for k in range(8)]
    for x, y in zip(a["noisy"], b["noisy"], strict=True):
        assert x.tobytes() == y.tobytes()
    for x, y in zip(a["links"], b["links"], strict=True):
        assert x.keys() == y.keys()
        for name in x:
            assert x[name].dtype == y[name].dtype and x[name].tobytes() == y[name].tobytes(), name


@pytest.fixture(scope="module")
def in_process() -> dict:
    with make_executor(workers=1) as ctx:
        assert ctx.kind == "in-process"
        return run_all(ctx)


def test_two_worker_processes_give_identical_results(in_process):
    with make_executor(workers=2) as ctx:
        assert ctx.kind == "processes" and ctx.n_slots == 2
        assert_identical(run_all(ctx), in_process)


@pytest.mark.skipif(not HAVE_DASK, reason="dask.distributed is not installed (pip install 'kinreg[dask]')")
def test_a_dask_cluster_gives_identical_results(in_process):
    from distributed import LocalCluster

    with (LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                       dashboard_address=None) as cluster,
          make_executor(workers=7, scheduler=cluster.scheduler_address) as ctx):
        assert ctx.kind == "dask" and ctx.n_slots == 2
        assert_identical(run_all(ctx), in_process)


@pytest.mark.parametrize("workers", [1, 2])
def test_a_failing_task_raises_its_error(workers):
    with make_executor(workers=workers) as ctx, pytest.raises(ValueError, match="item 3"):
        parallel_map(fail_on_three, range(10), ctx)


def test_bad_settings_are_refused():
    with pytest.raises(ConfigError), make_executor(workers=0):
        pass
    if HAVE_DASK:
        with pytest.raises(ConfigError, match="Dask scheduler"), make_executor(scheduler="tcp://127.0.0.1:1",
                                                                                 connect_timeout_s=1):
            pass


def test_each_worker_uses_one_blas_and_openmp_thread_and_this_process_is_left_alone():
    before = thread_settings(0)
    with make_executor(workers=2) as ctx:
        in_workers = parallel_map(thread_settings, range(4), ctx)
    for settings in in_workers:
        assert settings["env"] == dict.fromkeys(THREAD_VARIABLES, "1")
        assert settings["blas"] in (1, None)
    assert thread_settings(0) == before  # the calling process keeps its settings (in-process runs)
    if before["blas"] is not None:
        assert in_workers[0]["blas"] == 1


def test_the_forkserver_preload_does_not_load_numpy_before_it_limits_the_threads():
    # BLAS reads its thread count when numpy loads: kinreg.run._worker_threads must set the
    # environment first, so nothing the executor imports may load numpy.
    import subprocess
    import sys

    code = "import sys, kinreg.run.executor; print('numpy' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_the_workers_start_in_the_background_and_outlive_the_thread_that_started_them():
    # make_executor starts the workers without waiting for them (a thread submits a task that does
    # nothing). The kernel ties the forkserver's life to the thread that started it: started from
    # that short-lived thread it would be terminated when the thread ends, and every worker with it.
    # A fresh process, so that no forkserver of an earlier test is running already.
    import subprocess
    import sys

    code = (
        "import threading, time\n"
        "from kinreg.run.executor import make_executor, parallel_map\n"
        "with make_executor(workers=2) as ctx:\n"
        "    starters = [t for t in threading.enumerate() if t.name == 'kinreg-start-workers']\n"
        "    print(len(starters))\n"
        "    for t in starters: t.join()\n"
        "    time.sleep(0.5)\n"
        "    print(parallel_map(abs, [-1, -2, -3, -4], ctx))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split("\n")[:2] == ["1", "[1, 2, 3, 4]"]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the parent-death signal is Linux's")
def test_a_worker_whose_parent_ended_before_it_asked_to_end_with_it_ends_at_once():
    # A worker forked by the forkserver reaches its initialiser after the server (and the caller)
    # may have ended: it knows the server's pid, and a parent that is not the server ends it.
    import signal
    import subprocess

    code = "import os; from kinreg.run.executor import die_with_parent; die_with_parent(parent_pid={}); print('alive')"
    ended = subprocess.run([sys.executable, "-c", code.format("os.getpid()")], capture_output=True, text=True)
    assert (ended.returncode, ended.stdout) == (-signal.SIGTERM, "")
    kept = subprocess.run([sys.executable, "-c", code.format("os.getppid()")], capture_output=True, text=True)
    assert (kept.returncode, kept.stdout) == (0, "alive\n")
