"""Where per-scan and per-pair work runs: in this process, in local worker processes, or on a
Dask distributed cluster. Only :mod:`concurrent.futures` executors; no scheduler of our own.

- ``workers=1``: in this process, one task after the other (debugging, tests, profiling).
- ``workers=N > 1`` (``None``: every core): a :class:`~concurrent.futures.ProcessPoolExecutor`
  started with ``forkserver`` (``spawn`` where the platform has no forkserver). Not ``fork``:
  the parent holds threads (lazrs' decoder pool, a progress renderer, BLAS) and forking a
  threaded process can copy a held lock into the child and deadlock it. ``forkserver`` forks the
  workers from a small clean server process, so each worker starts without the parent's
  threads and memory, and faster than ``spawn`` (the interpreter is not started from scratch
  per worker).
- ``scheduler="tcp://host:8786"``: ``dask.distributed.Client(address).get_executor()``; dask is
  imported only then (the optional extra ``kinreg[dask]``).

One thread per local worker: N workers already keep N cores busy, so each worker limits BLAS
(OpenBLAS, MKL, BLIS), OpenMP and numexpr to one thread (:data:`THREAD_VARIABLES`);
otherwise every worker would start a pool per core and they would fight over the cores. The
variables must be set before a worker loads those libraries, so they are set in the forkserver
itself (its first preloaded module is :mod:`kinreg.run._worker_threads`, before the tasks' modules
(:mod:`kinreg.run.planes_stage`, ...) load numpy; ``__main__`` is not preloaded), and again in each
worker's initialiser, which also limits pools already loaded when ``threadpoolctl`` is installed.
The calling process is left as it is: in-process runs (``workers=1``) keep every BLAS thread.
Dask workers are configured by their cluster (Dask's nanny already sets these variables to 1).

The functions given to :func:`parallel_map` must be importable top-level functions of a module
(not lambdas, closures or functions defined in ``__main__`` of a script run by a worker), and
their arguments and results must be picklable: process pools and Dask move them between
processes with pickle. That is kinreg talking to its own workers; nothing a user supplies is
unpickled. Keep arguments small (a scan index and a spill path, not the scan's points): every
argument is copied to the worker.

Results come back in input order whatever the number of workers, and the tasks themselves do
not depend on it, so results are identical for any ``workers`` and for a cluster.

Local workers die with the calling process, however it ends. The pool's queues keep a worker
waiting for work forever once the caller is gone, and every worker holds the forkserver's
"alive" pipe open, so without help a killed ``kinreg`` leaves the forkserver and its workers
behind. On Linux each link of the chain asks the kernel for SIGTERM when its parent ends
(``prctl(PR_SET_PDEATHSIG)``, :func:`die_with_parent`): the forkserver (in its preloaded
module) when the calling process ends, each worker (in its initialiser) when the forkserver
ends. A worker also ignores SIGINT: Ctrl-C reaches the whole process group, and it is the
calling process that decides; when the ``with make_executor(...)`` block is left by an
exception (Ctrl-C, a failed task), the workers are terminated at once instead of finishing
their current tasks. Elsewhere (macOS) workers of a killed caller may outlive it. The kernel
ties the forkserver to the *thread* that started it (the one that first opened a pool; not the
thread that starts the workers in the background): a program that runs kinreg in a thread that
then ends loses that forkserver, and multiprocessing starts a new one for the next pool.
"""

from __future__ import annotations

import ctypes
import logging
import multiprocessing
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Executor, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from typing import Any, TypeVar

from kinreg.errors import ConfigError
from kinreg.heap import keep_freed_memory
from kinreg.progress import NullProgress, Progress
from kinreg.run.liveness import process_alive

log = logging.getLogger(__name__)

T = TypeVar("T")
R = TypeVar("R")

# Environment variables that size the thread pools of the numerical libraries in a worker.
THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
                    "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")


# prctl(2) option: the signal this process gets when its parent (thread) ends.
_PR_SET_PDEATHSIG = 1


def die_with_parent(sig: signal.Signals = signal.SIGTERM, ancestor_pid: int | None = None,
                    parent_pid: int | None = None) -> bool:
    """Ask the kernel to send ``sig`` to this process when its parent ends (Linux; elsewhere a
    no-op that returns False). If the parent (``parent_pid`` where the caller knows which process
    started it: then one that has ended before this call counts too), or ``ancestor_pid`` (a
    process further up the chain), has already ended by the time the request is in place, ``sig``
    is sent to this process at once. Returns whether the request was made. Only for kinreg's own
    child processes: the setting is cleared for children forked from this one."""
    if not sys.platform.startswith("linux"):
        return False
    parent = os.getppid() if parent_pid is None else parent_pid
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0:
            log.debug("prctl(PR_SET_PDEATHSIG) failed: %s", os.strerror(ctypes.get_errno()))
            return False
    except (OSError, AttributeError):  # no libc with prctl
        return False
    # The parent may have ended before the request: then no signal will come.
    if os.getppid() != parent or (ancestor_pid is not None and not process_alive(ancestor_pid)):
        os.kill(os.getpid(), sig)
    return True



def start_worker(caller_pid: int) -> None:
    """Initialiser of every local worker process: ends with its parent (the forkserver, which
    ends with ``caller_pid``), leaves SIGINT to the caller, one BLAS/OpenMP thread (see the
    module docstring). Never called in the calling process."""
    # A worker forked by the forkserver knows its parent from the server's preloaded module: the
    # server may have ended (with the caller) between the fork and this, and the worker's parent
    # is then another process, whatever state the caller's exit is in.
    server = sys.modules.get("kinreg.run._worker_threads")
    die_with_parent(ancestor_pid=caller_pid, parent_pid=getattr(server, "SERVER_PID", None))
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    limit_worker_threads()
    keep_freed_memory()  # a worker's next scan reuses the pages of the last one


def limit_worker_threads() -> None:
    """One BLAS/OpenMP thread in a local worker process or the forkserver (see the module
    docstring). Never called in the calling process."""
    for name in THREAD_VARIABLES:
        os.environ[name] = "1"
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return
    threadpool_limits(limits=1)  # pools of libraries this worker loaded before the variables were set


class InProcessExecutor(Executor):
    """Runs each task at submission, in the calling thread: no pool, plain tracebacks."""

    def submit(self, fn: Callable[..., R], /, *args: Any, **kwargs: Any) -> Future[R]:
        future: Future[R] = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as e:  # handed to the caller through the future, as a pool does
            future.set_exception(e)
        return future


@dataclass(frozen=True)
class ExecutorContext:
    """An open executor and how many tasks it runs at once (``n_slots``)."""

    executor: Executor
    n_slots: int
    kind: str  # "in-process", "processes" or "dask"

    def map(self, fn: Callable[[T], R], iterable: Iterable[T], chunksize: int = 1) -> Iterator[R]:
        """``fn`` over ``iterable``, results in input order (``chunksize`` batches tasks for a
        process pool; ignored elsewhere)."""
        if isinstance(self.executor, ProcessPoolExecutor):
            return self.executor.map(fn, iterable, chunksize=chunksize)
        return self.executor.map(fn, iterable)


def in_process() -> ExecutorContext:
    """The executor that runs every task in this process (the default of the stages)."""
    return ExecutorContext(InProcessExecutor(), 1, "in-process")


def default_workers() -> int:
    """The cores this process may use (the affinity mask, not the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover  (macOS, Windows)
        return max(1, os.cpu_count() or 1)


def _mp_context() -> multiprocessing.context.BaseContext:
    methods = multiprocessing.get_all_start_methods()
    if "forkserver" not in methods:
        return multiprocessing.get_context("spawn")
    context = multiprocessing.get_context("forkserver")
    # Effective when this starts the forkserver (the first pool of the process): workers are forked
    # from a server that has set the thread variables before it loaded numpy (not __main__, which
    # may import it first). Then it imports the modules of the workers' tasks (kinreg.run.planes_stage,
    # link_stage, large_outputs: numpy, scipy, most of kinreg; about a CPU second) once, which every
    # worker forked from it would otherwise import again when its first task is unpickled.
    context.set_forkserver_preload(["kinreg.run._worker_threads", "kinreg.run.planes_stage", "kinreg.run.link_stage",
                                    "kinreg.run.large_outputs"])
    return context


@contextmanager
def make_executor(workers: int | None = None, scheduler: str | None = None,
                  connect_timeout_s: float = 30.0) -> Iterator[ExecutorContext]:
    """Open the executor for ``workers`` local processes (``None``: every core, 1: in this
    process) or for the Dask scheduler at ``scheduler`` (then ``workers`` is ignored; give up
    connecting after ``connect_timeout_s``); shut it down on exit. Raises :class:`ConfigError`
    for ``workers < 1``, a missing dask or an unreachable scheduler.
    """
    if scheduler:
        with _dask_executor(scheduler, connect_timeout_s) as ctx:
            yield ctx
        return
    n = default_workers() if workers is None else int(workers)
    if n < 1:
        raise ConfigError(f"workers must be at least 1, got {n}")
    if n == 1:
        yield in_process()
        return
    context = _mp_context()
    pool = ProcessPoolExecutor(max_workers=n, mp_context=context, initializer=start_worker,
                               initargs=(os.getpid(),))
    starter = _start_workers(pool, context)
    try:
        yield ExecutorContext(pool, n, "processes")
    except BaseException:
        starter.join()
        _stop_now(pool)  # the caller gives up: no waiting for the tasks that are running
        raise
    finally:
        starter.join()
        pool.shutdown(wait=True, cancel_futures=True)


def _start_workers(pool: ProcessPoolExecutor, context: multiprocessing.context.BaseContext) -> threading.Thread:
    """Start ``pool``'s workers now, while the caller reads and slices the cloud, not when the
    first planes are wanted, and without waiting for them: the forkserver imports the tasks'
    module (numpy, scipy, kinreg; about a CPU second) before it forks the first worker, and the
    first task's ``submit`` waits for that. The forkserver itself is started from this (the
    calling) thread, which the kernel ties its life to (see the module's docstring); a thread
    then submits a task that does nothing, which forks the workers from it."""
    if context.get_start_method() == "forkserver":
        from multiprocessing import forkserver

        forkserver.ensure_running()  # starts the server process, does not wait for its imports
    starter = threading.Thread(target=_submit_nothing, args=(pool,), name="kinreg-start-workers", daemon=True)
    starter.start()
    return starter


def _submit_nothing(pool: ProcessPoolExecutor) -> None:
    # A pool the caller has shut down already, or workers that cannot start (the caller's own
    # first task then raises it, with one line and not a thread's traceback).
    with suppress(Exception):
        pool.submit(os.getpid)


def _stop_now(pool: ProcessPoolExecutor) -> None:
    """Shut ``pool`` down and terminate its workers, also those in the middle of a task."""
    # concurrent.futures has no public way to reach the workers before Python 3.14
    # (terminate_workers()); shutdown() forgets them, so take them first.
    processes = list((getattr(pool, "_processes", None) or {}).values())
    # Shut down before terminating: the pool's manager thread then drops the cancelled tasks before
    # it sees the workers gone (else Python 3.11 fails in that thread setting a cancelled future).
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        process.terminate()
    for process in processes:
        process.join(timeout=5.0)


@contextmanager
def _dask_executor(address: str, timeout_s: float) -> Iterator[ExecutorContext]:
    try:
        from distributed import Client
    except ImportError:
        raise ConfigError("--scheduler needs dask: pip install 'kinreg[dask]'") from None
    try:
        client = Client(address, timeout=f"{timeout_s}s", set_as_default=False)
    except (OSError, TimeoutError) as e:
        raise ConfigError(f"cannot connect to the Dask scheduler at {address}: {e}") from None
    try:
        n_slots = max(1, sum(client.nthreads().values()))
        # pure=False: never let Dask merge two submissions with equal arguments into one task.
        executor = client.get_executor(pure=False)
        log.info("Dask scheduler %s: %d worker threads", address, n_slots)
        yield ExecutorContext(executor, n_slots, "dask")
        executor.shutdown(wait=True)
    finally:
        client.close()


def parallel_map(
    fn: Callable[[T], R],
    items: Iterable[T],
    executor: ExecutorContext,
    progress: Progress | None = None,
    max_in_flight: int | None = None,
    on_result: Callable[[int, R], None] | None = None,
) -> list[R]:
    """``[fn(x) for x in items]`` on ``executor``, in input order; ``progress.advance(1)`` as each
    task finishes (in completion order, from the calling thread). The caller starts and finishes
    the progress stage.

    At most ``max_in_flight`` tasks (default four per slot) are submitted ahead, so ``items`` may
    be a lazy generator and only that many arguments and unread results are alive at once
    beyond the returned list. ``on_result(index, result)`` is called in the calling thread as each
    task finishes (e.g. to store it in the stage cache, so that a killed run keeps what it did).
    The first task that raises cancels the rest and its exception propagates.
    """
    progress = progress or NullProgress()
    limit = max_in_flight or 4 * executor.n_slots
    results: dict[int, R] = {}
    running: set[Future[R]] = set()
    index_of: dict[Future[R], int] = {}
    it = iter(items)
    exhausted = False
    n_submitted = 0
    try:
        while True:
            while not exhausted and len(running) < limit:
                try:
                    item = next(it)
                except StopIteration:
                    exhausted = True
                    break
                future = executor.executor.submit(fn, item)
                index_of[future] = n_submitted
                running.add(future)
                n_submitted += 1
            if not running:
                break
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            for future in done:
                running.discard(future)
                index = index_of.pop(future)
                results[index] = future.result()  # raises the task's exception
                if on_result is not None:
                    on_result(index, results[index])
                progress.advance(1)
    finally:
        for future in running:
            future.cancel()
    return [results[k] for k in range(n_submitted)]
