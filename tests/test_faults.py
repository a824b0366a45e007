"""Faults of ``kinreg process`` (issue 17, items 3-5): two runs on one output folder, a killed
parent with local workers, a failure late in the run.

- One writer per folder: a second run is refused in one line naming the first one's pid, changes
  nothing in the folder and does not disturb the first; a lock left by a killed run is taken over.
- Workers die with their parent: after SIGKILL (SIGTERM, SIGINT) of ``kinreg process --workers 2``
  every process it started (forkserver, workers, resource tracker) is gone within seconds.
- No finished-looking outputs of an unfinished run: a failure while writing ``sequence.e57``
  leaves no output at all, and the outputs of an earlier run stay as they were; a run killed
  while moving its outputs into place is completed by the next one.
"""

from __future__ import annotations

import errno
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from kinreg_cli.main import main
from test_resume import outputs

from kinreg.config import load_config
from kinreg.io import e57_writer
from kinreg.report.cloud_views import FIGURES_DIR
from kinreg.run import output_folder
from kinreg.run.liveness import process_alive
from kinreg.run.output_folder import CACHE_FOLDER, LOCK_FILE, STAGING_FOLDER, output_folder_lock
from kinreg.run.pipeline import OUTPUT_FILES, ProcessInputs, process
from kinreg.simulation.files import write_run
from kinreg.simulation.run import SimulationConfig, simulate_run

ROOT = Path(__file__).resolve().parents[1]
# The child kinreg must import this checkout, whatever is installed.
CHILD_ENV = {**os.environ, "PYTHONPATH": os.pathsep.join(
    [str(ROOT), str(ROOT / "cli"), *filter(None, [os.environ.get("PYTHONPATH")])])}


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two simulated 24 s runs (4 scans each; ``data`` and ``other``), a config with the spill in
    the test's folder, and the outputs of an uninterrupted run of ``data`` (``reference``)."""
    root = tmp_path_factory.mktemp("faults")
    write_run(simulate_run(SimulationConfig(seed=5, duration_s=24.0)), root / "data")
    write_run(simulate_run(SimulationConfig(seed=6, duration_s=24.0)), root / "other")
    (root / "spill").mkdir()
    (root / "kinreg.toml").write_text(f'[input]\nchunk_points = 20000\n[slicing]\ntemp_dir = "{root / "spill"}"\n')
    process(inputs(root), root / "reference", load_config(root / "kinreg.toml"))
    return root


def inputs(root: Path, data: str = "data") -> ProcessInputs:
    return ProcessInputs(root / data / "run_trajectory.txt", root / data / "run_cloud.laz")


def cli_args(root: Path, out: Path, *extra: str, data: str = "data", workers: int = 1) -> list[str]:
    return ["process", "-t", str(root / data / "run_trajectory.txt"), "-c", str(root / data / "run_cloud.laz"),
            "-o", str(out), "--config", str(root / "kinreg.toml"), "--workers", str(workers), *extra]


def cli(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    """Exit code and standard error of ``kinreg`` run in this process."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as info:
        main(args)
    code = info.value.code
    return (code if isinstance(code, int) else 0), capsys.readouterr().err


def snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    """Every file and folder below ``folder``: size and modification time."""
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(folder.rglob("*"))}


def start_kinreg(args: list[str], stderr: Path) -> subprocess.Popen:
    # Standard error into a file, not a pipe: a pipe would stay open as long as any process that
    # inherited it lives, and reading it would wait for exactly the leftovers this file tests.
    with stderr.open("w") as err:
        # Ctrl-C as in a terminal: a SIGINT disposition of "ignore" (set in this test process by
        # something else, e.g. a library's worker set-up) would be inherited through exec, and
        # Python leaves an ignored SIGINT ignored.
        return subprocess.Popen([sys.executable, "-m", "kinreg_cli", *args], stdout=subprocess.DEVNULL,
                                stderr=err, env=CHILD_ENV, cwd=ROOT,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def wait_for(condition, proc: subprocess.Popen, what: str, stderr: Path, timeout_s: float = 180.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if proc.poll() is not None:
            pytest.fail(f"kinreg process ended (code {proc.returncode}) before {what}: {stderr.read_text()}")
        if time.monotonic() > deadline:
            proc.kill()
            pytest.fail(f"no {what} after {timeout_s} s")
        time.sleep(0.01)


# --------------------------------------------------------------------------- one writer per folder


def test_a_second_run_is_refused_while_the_first_writes_and_the_first_is_not_disturbed(
    run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out, stderr = tmp_path / "out", tmp_path / "first.err"
    first = start_kinreg(cli_args(run, out), stderr)
    try:
        # the first is well into its work: it holds the lock and has stored the slicing
        wait_for(lambda: list((out / CACHE_FOLDER).glob("slice/*.json")), first, "the slicing stored", stderr)
        assert (out / LOCK_FILE).read_text() == f"{first.pid}\n"
        expected = f"kinreg: error: {out}: another kinreg (pid {first.pid}) is writing here\n"
        for extra, data in (((), "data"), (("--resume",), "data"), (("--resume",), "other"),
                            (("--overwrite",), "other")):
            assert cli(cli_args(run, out, *extra, data=data), capsys) == (1, expected), (extra, data)
        assert first.wait(timeout=300) == 0, stderr.read_text()
    finally:
        first.kill()
        first.wait()
    assert outputs(out) == outputs(run / "reference")
    assert {p.name for p in out.iterdir()} == {*OUTPUT_FILES, CACHE_FOLDER, FIGURES_DIR}  # the lock went with the run


def test_of_two_runs_started_together_one_runs_and_the_other_is_refused(run: Path, tmp_path: Path) -> None:
    out = tmp_path / "together"
    procs = [start_kinreg(cli_args(run, out, *extra), tmp_path / f"{k}.err")
             for k, extra in enumerate([(), ("--resume",)])]
    try:
        codes = [proc.wait(timeout=300) for proc in procs]
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()
    assert sorted(codes) == [0, 1], [(tmp_path / f"{k}.err").read_text() for k in range(2)]
    winner, loser = (0, 1) if codes[0] == 0 else (1, 0)
    assert (tmp_path / f"{loser}.err").read_text() == \
        f"kinreg: error: {out}: another kinreg (pid {procs[winner].pid}) is writing here\n"
    assert outputs(out) == outputs(run / "reference")


def test_a_refused_run_changes_nothing_in_the_folder(run: Path, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """Held here (a second open of the lock file conflicts like another process): not even
    ``--overwrite``, which would delete the cache, or a staging folder it would delete, is done."""
    out = tmp_path / "held"
    shutil.copytree(run / "reference", out)
    (out / STAGING_FOLDER).mkdir()
    (out / STAGING_FOLDER / "stations.csv").write_text("being written\n")
    with output_folder_lock(out):
        before = snapshot(out)
        for extra in ((), ("--resume",), ("--overwrite",)):
            code, err = cli(cli_args(run, out, *extra), capsys)
            assert (code, err) == (1, f"kinreg: error: {out}: another kinreg (pid {os.getpid()}) is writing here\n")
        assert snapshot(out) == before
    assert not (out / LOCK_FILE).exists()


def test_the_lock_of_a_killed_run_is_taken_over(run: Path, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "stale"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from pathlib import Path; "
         "from kinreg.run.output_folder import output_folder_lock\n"
         f"with output_folder_lock(Path({str(out)!r})):\n    print('held', flush=True); time.sleep(600)"],
        stdout=subprocess.PIPE, text=True, env=CHILD_ENV)
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "held\n"
        assert cli(cli_args(run, out), capsys)[1].endswith(f"another kinreg (pid {holder.pid}) is writing here\n")
    finally:
        holder.kill()
        holder.wait()
    assert (out / LOCK_FILE).read_text() == f"{holder.pid}\n"  # left behind, and no process holds it
    with output_folder_lock(out):
        assert (out / LOCK_FILE).read_text() == f"{os.getpid()}\n"
    assert not (out / LOCK_FILE).exists()


# --------------------------------------------------------------------------- workers die with their parent


def _processes() -> dict[int, tuple[int, str, str]]:
    """pid -> (parent pid, state, start time) of every process."""
    found = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()  # after "pid (name) "
        found[int(entry)] = (int(fields[1]), fields[0], fields[19])
    return found


def _descendants(pid: int) -> dict[int, str]:
    """pid -> start time of every living descendant of ``pid``."""
    processes, found, parents = _processes(), {}, {pid}
    while parents:
        children = {p: start for p, (ppid, state, start) in processes.items() if ppid in parents and p not in found}
        found.update(children)
        parents = set(children)
    return found


def _alive(processes: dict[int, str]) -> list[int]:
    """Those of ``processes`` (pid -> start time) still running (a zombie has ended; a new process
    with a recycled pid is another one)."""
    now = _processes()
    return [pid for pid, start in processes.items() if pid in now and now[pid][1] != "Z" and now[pid][2] == start]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="zombies are read from /proc")
def test_a_process_that_ended_is_not_alive_before_it_is_reaped() -> None:
    # A worker that reaches its initialiser after the forkserver has ended checks the killed kinreg
    # itself: a zombie until whoever started it waits for it, and then it has ended already.
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    try:
        os.waitid(os.P_PID, child.pid, os.WEXITED | os.WNOWAIT)  # ended, not reaped: a zombie
        assert _processes()[child.pid][1] == "Z"
        assert not process_alive(child.pid)
    finally:
        child.wait()
    assert not process_alive(child.pid)
    assert process_alive(os.getpid())


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the parent-death signal is Linux's")
@pytest.mark.parametrize("sig", [
    signal.SIGKILL,
    pytest.param(signal.SIGTERM, marks=pytest.mark.slow),  # to the workers the same as SIGKILL
    signal.SIGINT,
], ids=lambda sig: sig.name)
def test_the_workers_end_with_their_parent(sig: signal.Signals, tmp_path: Path) -> None:
    stderr, config = tmp_path / "kinreg.err", tmp_path / "kinreg.toml"
    config.write_text(f'[slicing]\ntemp_dir = "{tmp_path}"\n')  # the spill a killed run leaves goes with the test
    proc = start_kinreg(["process", "-t", "sample_data/run_trajectory.txt", "-c", "sample_data/run_cloud.laz",
                         "-o", str(tmp_path / "out"), "--workers", "2", "--config", str(config)], stderr)
    try:
        # the forkserver and the resource tracker are its children, the workers its grandchildren
        wait_for(lambda: sum(_processes().get(p, (0,))[0] != proc.pid for p in _descendants(proc.pid)) >= 2,
                 proc, "two worker processes", stderr)
        started = _descendants(proc.pid)
    finally:
        proc.send_signal(sig)
        proc.wait()
    t0 = time.monotonic()
    while _alive(started) and time.monotonic() - t0 < 10.0:
        time.sleep(0.02)
    left = _alive(started)
    for pid in left:  # not to leave them to the next test
        os.kill(pid, signal.SIGKILL)
    assert not left, f"{len(left)} of {len(started)} processes alive {time.monotonic() - t0:.1f} s after {sig.name}"
    assert time.monotonic() - t0 < 5.0
    print(f"{len(started)} processes gone {time.monotonic() - t0:.2f} s after {sig.name}")
    if sig is signal.SIGINT:
        assert proc.returncode == 130, (proc.returncode, stderr.read_text(), signal.getsignal(signal.SIGINT))
        assert stderr.read_text() == "kinreg: interrupted\n"  # no traceback of a worker or the pool
    else:
        assert proc.returncode == -sig
        assert list(tmp_path.glob("kinreg-slices-*"))  # killed: the spill is kept for --resume


# --------------------------------------------------------------------------- no finished-looking outputs


@pytest.fixture
def disk_full_in_the_e57(monkeypatch: pytest.MonkeyPatch) -> None:
    """The disk fills while ``sequence.e57`` is written (its second page write; the file goes out
    in small buffers), after every other large output is complete."""
    monkeypatch.setattr(e57_writer, "FILE_BUFFER_BYTES", 4096)
    original = e57_writer._PagedFile._write_pages
    calls = []

    def write_then_fail(file: e57_writer._PagedFile, k: int) -> None:
        calls.append(k)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        original(file, k)

    monkeypatch.setattr(e57_writer._PagedFile, "_write_pages", write_then_fail)


@pytest.mark.usefixtures("disk_full_in_the_e57")
def test_a_late_failure_leaves_no_output(run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "late"
    code, err = cli(cli_args(run, out), capsys)
    assert code == 1
    assert re.fullmatch(rf"kinreg: error: {re.escape(str(out / 'sequence.e57'))}: cannot write scan 'qs_\d+': "
                        "No space left on device\n", err), err
    # corrected.laz and trajectory_corrected.txt were complete; none of them is there, nor a temporary
    assert {p.name for p in out.iterdir()} == {CACHE_FOLDER}


@pytest.mark.usefixtures("disk_full_in_the_e57")
def test_a_late_failure_leaves_the_outputs_of_an_earlier_run_as_they_were(
    run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "earlier"
    shutil.copytree(run / "reference", out)
    before = snapshot(out)
    code, _ = cli(cli_args(run, out, "--overwrite"), capsys)  # everything is written again
    assert code == 1
    after = snapshot(out)
    assert {k: v for k, v in after.items() if k.split(os.sep)[0] != CACHE_FOLDER} == \
        {k: v for k, v in before.items() if k.split(os.sep)[0] != CACHE_FOLDER}  # not touched
    assert outputs(out) == outputs(run / "reference")


def test_a_run_killed_while_moving_its_outputs_in_is_completed_by_the_next(
    run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "moving"
    process(inputs(run, "other"), out, load_config(run / "kinreg.toml"))  # an earlier run of other data
    earlier = outputs(out)
    moved = []
    original = os.replace

    def replace_then_die(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> None:
        if Path(src).parent.name == STAGING_FOLDER and Path(dst).parent == out:
            if len(moved) == 3:  # three outputs of the new run are in place
                raise KeyboardInterrupt  # as good as a kill here: nothing of kinreg runs after it
            moved.append(Path(dst).name)
        original(src, dst)

    monkeypatch.setattr(output_folder.os, "replace", replace_then_die)
    with pytest.raises(KeyboardInterrupt):
        process(inputs(run), out, load_config(run / "kinreg.toml"), overwrite=True)
    monkeypatch.undo()
    assert len(moved) == 3 and "report.json" not in moved
    assert not (out / "report.json").exists()  # a mixed folder never looks finished
    assert (out / STAGING_FOLDER / ".commit.json").is_file()
    # the next run completes the move before it looks at the folder: it finds the new run finished
    summary = process(inputs(run), out, load_config(run / "kinreg.toml"), resume=True)
    assert summary.stage_cache["corrected cloud"] == {"reused": 1, "computed": 0}
    assert outputs(out) == outputs(run / "reference") != earlier
    assert {p.name for p in out.iterdir()} == {*OUTPUT_FILES, CACHE_FOLDER, FIGURES_DIR}


def test_the_resource_tracker_of_a_run_does_not_warn_after_an_interrupt(capsys: pytest.CaptureFixture[str]) -> None:
    # Ctrl-C ends the workers while their queues' semaphores are being unlinked; Python's resource
    # tracker (its own process) then warned of leaked semaphores after "kinreg: interrupted". It is
    # started with this interpreter's -W flags, which kinreg's entry point sets.
    from multiprocessing import util

    with pytest.raises(SystemExit):
        main(["--help"])
    assert "-Wignore::UserWarning:multiprocessing.resource_tracker" in util._args_from_interpreter_flags()
