"""Mutation fuzzing of every reader through the ``kinreg`` command, in subprocesses (issue 17).

Seeded mutants (:mod:`fuzzing`) of LAS/LAZ, E57, trajectory text, reference-plane TOML and
configuration TOML go through ``kinreg info --full`` (``kinreg config --config`` for the
configuration), and a few known-wrong inputs through ``kinreg process`` on ``sample_data/``.
Asserted over all of them: no signal, no traceback, no internal error (exit 2), no hang; every
refusal at most 2 lines naming the file; no exit 0 for an input known to be wrong.

The default run takes every ``DEFAULT_STRIDE``-th mutant (under a minute); ``make test-slow``
runs all of them (600+).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from pathlib import Path

import laspy
import numpy as np
import pytest
from fuzzing import (
    REALDATA,
    ROOT,
    Mutant,
    Outcome,
    bit_flip_mutants,
    e57_mutants,
    las_header_mutants,
    problems,
    run_mutant,
    small_las,
    tally,
    toml_mutants,
    trajectory_mutants,
    truncation_mutants,
    write_e57,
)

from kinreg.config import KinregConfig, format_toml

SEED = 17
DEFAULT_STRIDE = 23
SAMPLE = ROOT / "sample_data"

Corpus = dict[str, tuple[Callable[[Path], list[object]], Callable[[], Iterator[Mutant]]]]


def corpus(folder: Path) -> Corpus:
    """Per reader: the command for a mutant's path, and a generator of its mutants (seeded)."""
    rng = np.random.default_rng(SEED)
    laz14 = small_las(folder / "base14.laz")
    las14 = small_las(folder / "base14.las", n_points=3000)
    las_bases = [(laz14, "laz14"), (las14, "las14")]
    las_bases += [(REALDATA / n, n.split("_")[0]) for n in ("autzen_trim.laz", "vegetation_1_3.las")
                  if (REALDATA / n).exists()]
    e57 = write_e57(folder / "base.e57", n_scans=2, n_points=300)
    trajectory = "\n".join((SAMPLE / "run_trajectory.txt").read_text().splitlines()[:400]) + "\n"
    reference = (SAMPLE / "reference.toml").read_text()
    config = format_toml(KinregConfig())

    def las() -> Iterator[Mutant]:
        for path, tag in las_bases:
            data = path.read_bytes()
            yield from las_header_mutants(data, tag, path.suffix)
            yield from bit_flip_mutants(data, f"{tag}/header", path.suffix, rng, 10, (0, 375))
            yield from bit_flip_mutants(data, tag, path.suffix, rng, 10)
            yield from truncation_mutants(data, tag, path.suffix, rng, 8)

    def e57_files() -> Iterator[Mutant]:
        yield from e57_mutants(e57.read_bytes(), "e57", rng, 10, 30, 8)
        if (REALDATA / "pdal_A_B.e57").exists():  # no point times: `info` does not read its points
            yield from e57_mutants((REALDATA / "pdal_A_B.e57").read_bytes(), "pdal", rng, 5, 15, 4,
                                   points_read=False)

    return {
        "las": (lambda p: ["info", "--full", p], las),
        "e57": (lambda p: ["info", "--full", p], e57_files),
        "trajectory": (lambda p: ["info", p], lambda: trajectory_mutants(trajectory, "traj", rng, 20)),
        "reference": (lambda p: ["info", p], lambda: toml_mutants(reference, "ref", rng, 20,
                                                                          "plane_construction_accuracy_m")),
        "config": (lambda p: ["config", "--config", p], lambda: toml_mutants(config, "cfg", rng, 20, "window_s")),
    }


def run_corpus(folder: Path, stride: int) -> tuple[dict[str, list[Outcome]], dict[str, Mutant]]:
    work = folder / "mutants"
    work.mkdir()
    outcomes: dict[str, list[Outcome]] = {}
    mutants: dict[str, Mutant] = {}
    for reader, (args, generate) in corpus(folder).items():
        outcomes[reader] = []
        for mutant in itertools.islice(generate(), 0, None, stride):
            assert mutant.name not in mutants, mutant.name
            mutants[mutant.name] = mutant
            outcomes[reader].append(run_mutant(mutant, work, args))
            (work / "out").mkdir(exist_ok=True)
    return outcomes, mutants


def figures(outcomes: dict[str, list[Outcome]], mutants: dict[str, Mutant]) -> str:
    lines = []
    for reader, found in outcomes.items():
        wrong = sum(mutants[o.mutant].wrong for o in found)
        lines.append(f"{reader}: {len(found)} mutants ({wrong} known wrong): {tally(found)}")
    return "\n".join(lines)


def check(outcomes: dict[str, list[Outcome]], mutants: dict[str, Mutant]) -> None:
    every = [o for found in outcomes.values() for o in found]
    bad = problems(every, mutants)
    assert not bad, figures(outcomes, mutants) + "\n" + "\n".join(bad)


def test_fuzz_readers_sample(tmp_path: Path) -> None:
    outcomes, mutants = run_corpus(tmp_path, DEFAULT_STRIDE)
    assert all(outcomes.values()), "every reader gets mutants"
    print(figures(outcomes, mutants))
    check(outcomes, mutants)
    # Known-wrong inputs are among them for every reader, and they are refused (not merely not
    # crashing); the real files beside the clone (../shared/realdata) add more where present.
    for reader, found in outcomes.items():
        assert any(mutants[o.mutant].wrong for o in found), f"no known-wrong {reader} mutant"
    assert sum(m.wrong for m in mutants.values()) >= (15 if REALDATA.is_dir() else 10)


@pytest.mark.slow
def test_fuzz_readers_all(tmp_path: Path) -> None:
    outcomes, mutants = run_corpus(tmp_path, 1)
    print(figures(outcomes, mutants))
    assert len(mutants) >= 300
    check(outcomes, mutants)


# --------------------------------------------------------------------------- kinreg process


def process_mutants(folder: Path, every: bool) -> Iterator[tuple[str, list[object], Path]]:
    """Known-wrong inputs for ``kinreg process`` on the sample run: (name, extra args, the bad file)."""
    trajectory = SAMPLE / "run_trajectory.txt"
    cloud = SAMPLE / "run_cloud.laz"
    rows = trajectory.read_text().splitlines()

    def write(name: str, data: bytes | str) -> Path:
        path = folder / name
        path.write_bytes(data.encode() if isinstance(data, str) else data)
        return path

    bad_traj = write("nan_traj.txt", "\n".join([*rows[:500], "nan" + rows[500][rows[500].index(" "):],
                                                 *rows[501:]]) + "\n")
    yield "trajectory NaN time", ["-t", bad_traj, "-c", cloud], bad_traj
    deep = write("deep.toml", "x = " + "[" * 100_000 + "]" * 100_000 + "\n")
    yield "config nested 100000 deep", ["-t", trajectory, "-c", cloud, "--config", deep], deep
    header = bytearray(cloud.read_bytes())
    header[139:147] = np.float64(np.nan).tobytes()  # y scale
    nan_scale = write("nan_scale.laz", bytes(header))
    yield "cloud y scale NaN", ["-t", trajectory, "-c", nan_scale], nan_scale
    if not every:
        return
    nan_ref = write("nan_ref.toml", (SAMPLE / "reference.toml").read_text().replace("0.05", "nan", 1))
    yield "reference accuracy NaN", ["-t", trajectory, "-c", cloud, "--reference", nan_ref], nan_ref
    static = bytearray((SAMPLE / "static.e57").read_bytes())
    from fuzzing import e57_first_data_packet, e57_fix_checksums

    packet = e57_first_data_packet(bytes(static))
    static[packet] = 255
    bad_static = write("packet.e57", bytes(e57_fix_checksums(static, [packet])))
    yield "static E57 data packet type 255", ["-t", trajectory, "-c", cloud, "--static", bad_static], bad_static
    las = laspy.read(cloud)
    las.gps_time = np.asarray(las.gps_time) + 18.0
    shifted = folder / "gps18.laz"
    las.write(shifted)
    yield "cloud 18 s later", ["-t", trajectory, "-c", shifted], shifted
    data = cloud.read_bytes()
    start = int.from_bytes(data[96:100], "little")
    table = int.from_bytes(data[start:start + 8], "little")
    cut = write("chunk_table_byte.laz", data[:table + 5] + data[table + 6:])
    yield "cloud one byte deleted in the chunk table", ["-t", trajectory, "-c", cut], cut
    for k, mutant in enumerate(truncation_mutants(data, "cloud", ".laz", np.random.default_rng(SEED), 3)):
        path = write(f"cut_{k}.laz", mutant.data)
        yield mutant.name, ["-t", trajectory, "-c", path], path


def run_process_mutants(folder: Path, every: bool) -> list[str]:
    from fuzzing import classify, run_kinreg

    bad = []
    for k, (name, args, path) in enumerate(process_mutants(folder, every)):
        code, _, err = run_kinreg(["process", *args, "-o", folder / f"out{k}", "--workers", "1"], timeout_s=300)
        outcome = classify(name, code, err, path)
        if outcome.kind != "refused" or len(outcome.lines) > 2 or not outcome.names_file:
            bad.append(str(outcome))
    return bad


def test_fuzz_process_sample(tmp_path: Path) -> None:
    assert run_process_mutants(tmp_path, every=False) == []


@pytest.mark.slow
def test_fuzz_process_all(tmp_path: Path) -> None:
    assert run_process_mutants(tmp_path, every=True) == []
