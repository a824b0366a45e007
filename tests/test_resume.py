"""Resumable ``kinreg process``: a resumed run re-uses what did not change and gives the same
outputs as a run that went through, also after a SIGKILL (here: while slicing, while detecting
planes on two workers, while writing the corrected cloud).

"The same outputs" means byte-identical files, except ``report.json`` and ``report.html``,
which carry the run's timings and what it re-used from the stage cache (``timings_s`` and
``stage_cache``): those two are compared without them, everything else in them must be equal.
"""

from __future__ import annotations

import json
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

from kinreg.config import load_config
from kinreg.report.cloud_views import FIGURES_DIR
from kinreg.run.output_folder import CACHE_FOLDER
from kinreg.run.pipeline import OUTPUT_FILES, ProcessInputs, process
from kinreg.simulation.files import write_run
from kinreg.simulation.run import SimulationConfig, simulate_run

VOLATILE_REPORT_KEYS = ("timings_s", "stage_cache")


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A simulated 24 s run (4 scans), a config with the spill in the test's folder, and the
    outputs of an uninterrupted run (``reference``)."""
    root = tmp_path_factory.mktemp("resume")
    write_run(simulate_run(SimulationConfig(seed=5, duration_s=24.0)), root / "data")
    (root / "spill").mkdir()
    # small chunks: the corrected cloud takes a few writes, long enough to be caught and killed
    (root / "kinreg.toml").write_text(f'[input]\nchunk_points = 20000\n[slicing]\ntemp_dir = "{root / "spill"}"\n')
    summary = process(inputs(root), root / "reference", load_config(root / "kinreg.toml"))
    assert summary.stage_cache["planes"] == {"reused": 0, "computed": 4}
    assert not list((root / "spill").iterdir())  # a finished run deletes its spill
    return root


def inputs(root: Path) -> ProcessInputs:
    return ProcessInputs(root / "data" / "run_trajectory.txt", root / "data" / "run_cloud.laz")


def cli_args(root: Path, out: str, *extra: str, workers: int = 1) -> list[str]:
    return ["process", "-t", str(root / "data" / "run_trajectory.txt"), "-c", str(root / "data" / "run_cloud.laz"),
            "-o", str(root / out), "--config", str(root / "kinreg.toml"), "--workers", str(workers), *extra]


def outputs(folder: Path) -> dict[str, object]:
    """Everything of the outputs that must not depend on how the run got there."""
    found: dict[str, object] = {name: (folder / name).read_bytes() for name in OUTPUT_FILES
                                if name not in ("report.json", "report.html")}
    report = json.loads((folder / "report.json").read_text())
    found["report.json"] = {k: v for k, v in report.items() if k not in VOLATILE_REPORT_KEYS}
    html = (folder / "report.html").read_text()
    found["report.html"] = re.sub(r'<div class="card"><h3>Timings</h3>.*?</table></div>', "", html)
    assert found["report.html"] != html  # the timings card was there; the pattern takes out only it
    return found


def stage_cache(folder: Path) -> dict[str, dict[str, int]]:
    return json.loads((folder / "report.json").read_text())["stage_cache"]


def test_a_resume_with_nothing_changed_reuses_every_stage(run: Path) -> None:
    out = run / "unchanged"
    process(inputs(run), out, load_config(run / "kinreg.toml"), resume=True)  # a missing folder: afresh
    cloud_mtime = (out / "corrected.laz").stat().st_mtime_ns
    summary = process(inputs(run), out, load_config(run / "kinreg.toml"), resume=True)
    assert summary.stage_cache == {
        "slice": {"reused": 1, "computed": 0},  # no pass over the cloud
        "planes": {"reused": 4, "computed": 0},
        "link": {"reused": 1, "computed": 0},
        "block": {"reused": 0, "computed": 1},  # not stored: seconds, and the outputs are keyed by its result
        "corrected cloud": {"reused": 1, "computed": 0},
        "sequence E57": {"reused": 1, "computed": 0},
    }
    assert stage_cache(out) == summary.stage_cache
    assert (out / "corrected.laz").stat().st_mtime_ns == cloud_mtime  # kept, not written again
    assert outputs(out) == outputs(run / "reference")


def test_a_changed_block_section_redoes_the_links_and_block_and_what_follows(run: Path) -> None:
    out = run / "block_changed"
    shutil.copytree(run / "reference", out)  # a finished run (copy2 keeps the modification times)
    config = run / "block.toml"
    config.write_text((run / "kinreg.toml").read_text() + "[block]\nmax_relink_rounds = 0\n")
    summary = process(inputs(run), out, load_config(config), resume=True)
    # The outputs are keyed by the adjusted poses: made again where they moved, kept where not.
    moved = (out / "stations.csv").read_bytes() != (run / "reference" / "stations.csv").read_bytes()
    again = {"reused": 0, "computed": 1} if moved else {"reused": 1, "computed": 0}
    assert summary.stage_cache == {
        # the index is re-used; the points for sequence.e57 are read again if it is written again
        "slice": {"reused": 1, "computed": 1 if moved else 0},
        "planes": {"reused": 4, "computed": 0},
        # without relinking, the first links include the loop closures (they are not made later)
        "link": {"reused": 0, "computed": 1},
        "block": {"reused": 0, "computed": 1},
        "corrected cloud": again,
        "sequence E57": again,
    }
    assert not list((run / "spill").iterdir())
    process(inputs(run), run / "block_fresh", load_config(config))
    assert outputs(out) == outputs(run / "block_fresh")
    # and back: the planes and links are still there, the block result is the reference's again
    summary = process(inputs(run), out, load_config(run / "kinreg.toml"), resume=True)
    assert summary.stage_cache["planes"] == {"reused": 4, "computed": 0}
    assert outputs(out) == outputs(run / "reference")


def wait_for(condition, proc: subprocess.Popen, what: str, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if proc.poll() is not None:
            pytest.fail(f"kinreg process ended (code {proc.returncode}) before {what}: {proc.stderr.read()}")
        if time.monotonic() > deadline:
            pytest.fail(f"no {what} after {timeout_s} s")
        time.sleep(0.002)


def start_kinreg(run: Path, out: Path, *extra: str, workers: int = 1) -> subprocess.Popen:
    # Its own session, so that SIGKILL hits kinreg and its worker processes at once (a power cut).
    return subprocess.Popen([sys.executable, "-m", "kinreg_cli", *cli_args(run, out.name, *extra, workers=workers)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)


def kill(proc: subprocess.Popen) -> None:
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert proc.stderr is not None
    proc.stderr.close()


def assert_nothing_looks_finished(out: Path) -> None:
    """No output at all, not even the complete ones of the killed run: only hidden files (the
    cache, the staged outputs, the lock)."""
    names = {p.name for p in out.iterdir()}
    assert not names & set(OUTPUT_FILES)
    assert all(name.startswith(".") for name in names), names


def test_a_run_killed_twice_and_resumed_gives_the_outputs_of_an_uninterrupted_run(
    run: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = run / "killed"
    cache = out / CACHE_FOLDER
    n_planes = lambda: len(list((cache / "planes").glob("*.json")))  # noqa: E731

    # 1. SIGKILL during plane detection (on two workers), once some scans are stored
    proc = start_kinreg(run, out, workers=2)
    try:
        wait_for(lambda: n_planes() >= 1, proc, "a stored scan")
    finally:
        kill(proc)
    assert_nothing_looks_finished(out)
    n_planes_kept = n_planes()
    assert 1 <= n_planes_kept < 4
    assert [p.name for p in (run / "spill").iterdir()]  # the spill is kept for --resume

    # 2. resumed, and killed again while the corrected cloud is being written
    proc = start_kinreg(run, out, "--resume")
    try:
        wait_for(lambda: list(out.glob(".kinreg-staging/.corrected.tmp-*.laz")), proc,
                 "the corrected cloud being written")
    finally:
        kill(proc)
    assert_nothing_looks_finished(out)
    assert (out / ".kinreg-staging" / "trajectory_corrected.txt").is_file()  # complete, but not in place
    assert n_planes() == 4

    # 3. resumed to the end
    with pytest.raises(SystemExit) as info:
        main(cli_args(run, out.name, "--resume"))
    assert info.value.code == 0, capsys.readouterr().err
    assert stage_cache(out) == {
        "slice": {"reused": 1, "computed": 0},  # the kept spill: no new pass over the cloud
        "planes": {"reused": 4, "computed": 0},
        "link": {"reused": 1, "computed": 0},
        "block": {"reused": 0, "computed": 1},
        "corrected cloud": {"reused": 0, "computed": 1},
        "sequence E57": {"reused": 0, "computed": 1},
    }
    assert outputs(out) == outputs(run / "reference")
    assert not [p for p in out.iterdir() if ".tmp-" in p.name]  # the killed runs' temporaries are gone
    assert {p.name for p in out.iterdir()} == {*OUTPUT_FILES, CACHE_FOLDER, FIGURES_DIR}  # no staging, no lock
    assert not list((run / "spill").iterdir())


def test_the_folder_rules(run: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Without a flag an existing run is refused; --overwrite starts afresh (the cache is cleared)."""
    out = run / "rules"
    shutil.copytree(run / "reference", out)
    with pytest.raises(SystemExit) as info:
        main(cli_args(run, out.name))
    assert info.value.code == 1
    assert "already holds kinreg results; use --overwrite to replace them or --resume" in capsys.readouterr().err
    stale = out / CACHE_FOLDER / "planes" / "0123abcd.json"
    stale.write_text("{}")
    with pytest.raises(SystemExit) as info:
        main(cli_args(run, out.name, "--overwrite"))
    assert info.value.code == 0
    assert stage_cache(out)["planes"] == {"reused": 0, "computed": 4}
    assert not stale.exists()
    assert outputs(out) == outputs(run / "reference")


def test_an_unfinished_spill_is_not_used_and_is_deleted(run: Path) -> None:
    """A run killed while slicing leaves a partial spill and its record: the next run slices again
    (and deletes the partial spill) where it needs points."""
    out = run / "partial_spill"
    shutil.copytree(run / "reference", out)
    (out / "sequence.e57").unlink()  # so that points are needed
    (slice_key,) = [p.stem for p in (out / CACHE_FOLDER / "slice").glob("*.json")]
    partial = run / "spill" / "kinreg-slices-partial"
    partial.mkdir()
    (partial / "unit_000000.bin").write_bytes(b"\0" * 240)  # no .complete mark
    (out / CACHE_FOLDER / "spill.json").write_text(json.dumps({"key": slice_key, "folder": str(partial)}))
    summary = process(inputs(run), out, load_config(run / "kinreg.toml"), resume=True)
    assert summary.stage_cache["slice"] == {"reused": 1, "computed": 1}
    assert summary.stage_cache["sequence E57"] == {"reused": 0, "computed": 1}
    assert not partial.exists() and not list((run / "spill").iterdir())
    assert outputs(out) == outputs(run / "reference")
