"""Shorter windows where the drift smears the planes: beyond the planes' noise in any case (the
windows' length is also the correction's time resolution); between max_smear_share and the noise
only where the planes' offsets show it (shorter windows hold fewer planes: held-out building,
world drift, seed 8, smear 0.83 of the noise: 6 s windows 1.8 mm RMS, 3.5 s windows 2.7 mm)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from kinreg.config import SlicingConfig, load_config
from kinreg.estimate.slicing import shorter_window_s
from kinreg.estimate.snooping import chi2_quantile, models_rejected
from kinreg.types import ObservationKind, ObservationTest

OFFSET = ObservationKind.PLANE_OFFSET
FLOOR = ObservationKind.PLANE_OFFSET_FLOOR


def _group(kind: ObservationKind, n: int, vtpv_each: float) -> list[ObservationTest]:
    return [ObservationTest(k, kind, k, -1, vtpv_each, 1, 1.0, math.sqrt(vtpv_each), False, vtpv=vtpv_each)
            for k in range(n)]


def test_a_group_rejects_its_model_beyond_its_chi_square_over_its_redundancy():
    critical = chi2_quantile(1 - 0.001, 100) / 100  # about 1.45
    below = _group(OFFSET, 100, 0.98 * critical)
    tests = below + _group(FLOOR, 100, 1.02 * critical) + _group(ObservationKind.PLANE, 100, 10.0)  # not asked
    kinds = (OFFSET.value, FLOOR.value)
    assert list(models_rejected(tests, {}, kinds, 0.001)) == [FLOOR.value]
    # the residuals under the final weights times the variance factor those weights carry: the
    # a-priori model's misfit (a component of 2 on residuals that fit the final weights)
    assert math.isclose(models_rejected(_group(OFFSET, 100, 1.0), {OFFSET.value: 2.0}, kinds, 0.001)[OFFSET.value],
                        2.0)
    assert models_rejected(_group(OFFSET, 100, 1.0), {OFFSET.value: 1.2}, kinds, 0.001) == {}
    # too little redundancy to tell; a rejected observation is left out
    assert models_rejected(_group(OFFSET, 4, 10.0), {}, kinds, 0.001) == {}
    rejected = dataclasses.replace(_group(OFFSET, 1, 1e6)[0], rejected=True)
    assert models_rejected([*below, rejected], {}, kinds, 0.001) == {}


def test_a_smear_below_the_noise_counts_only_where_the_planes_show_it():
    planes = [tuple(SimpleNamespace(rms_m=0.01) for _ in range(5))]  # the planes' noise: 10 mm
    config = SlicingConfig()  # 6 s windows, max_smear_share 0.5, shown_smear_share 1.0, min 2 s

    def window(smear_mm: float, shown: bool) -> float | None:
        return shorter_window_s(6.0, np.array([smear_mm / 1000, np.nan]), planes, config, shown)  # type: ignore[arg-type]

    assert window(4.0, True) is None  # within half the noise: quasi-static
    assert window(7.0, False) is None  # the planes fit their model: the longer windows stand
    assert window(7.0, True) == 4.0  # 6 s * 5 / 7, in half seconds
    assert window(20.0, False) == 2.0  # beyond the noise in any case (6 s * 5 / 20 = 1.5, not below 2 s)
    assert shorter_window_s(6.0, np.array([0.02]), planes, dataclasses.replace(config, adaptive=False)) is None


def test_a_smear_the_planes_do_not_show_keeps_the_windows(tmp_path: Path) -> None:
    from kinreg.run.pipeline import ProcessInputs, process
    from kinreg.simulation.files import write_run
    from kinreg.simulation.run import SimulationConfig, simulate_run

    write_run(simulate_run(SimulationConfig(seed=5, duration_s=24.0)), tmp_path / "data")
    inputs = ProcessInputs(tmp_path / "data" / "run_trajectory.txt", tmp_path / "data" / "run_cloud.laz")
    some = "[slicing]\nmax_smear_share = 1e-9\nmin_window_s = 3.0\n"  # any smear is worth a look
    (tmp_path / "some.toml").write_text(some)
    (tmp_path / "any.toml").write_text(some + "shown_smear_share = 1e-9\n")  # and slices again
    kept = process(inputs, tmp_path / "kept", load_config(tmp_path / "some.toml"))
    slicing = json.loads((tmp_path / "kept" / "report.json").read_text())["slicing"]
    assert kept.n_stations == 4 and slicing["window_s"] == 6.0  # its planes' offsets fit their model
    again = process(inputs, tmp_path / "again", load_config(tmp_path / "any.toml"))
    slicing = json.loads((tmp_path / "again" / "report.json").read_text())["slicing"]
    assert again.n_stations == 8 and slicing["window_s"] == 3.0
