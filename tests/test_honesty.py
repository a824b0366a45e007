"""Honesty of the reported station sigmas end to end (slow: three simulated runs).

On repeated realisations of the sample scenario (other walk, drift and noise than the committed
run), the normalised station errors (error relative to the datum / reported sigma), pooled over
the runs, must have an RMS between 0.7 and 1.5. One run's stations share most of their error, so
the figure is judged on the pool (``benchmarks/eval_accuracy.py --seeds`` does the same with
more runs and the held-out scenario).
"""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from kinreg.config import KinregConfig
from kinreg.io.trajectory import read_trajectory
from kinreg.run.pipeline import ProcessInputs, process
from kinreg.simulation.files import write_run
from kinreg.simulation.run import config_from_dict, simulate_run

SAMPLE = Path(__file__).resolve().parents[1] / "sample_data"


@pytest.mark.slow
def test_pooled_normalised_station_errors_are_near_one(tmp_path):
    base = config_from_dict(json.loads((SAMPLE / "run_meta.json").read_text())["config"])
    z2 = []
    for seed in (2, 3, 4):
        data, out = tmp_path / f"data{seed}", tmp_path / f"out{seed}"
        write_run(simulate_run(dataclasses.replace(base, seed=seed)), data)
        process(ProcessInputs(data / "run_trajectory.txt", data / "run_cloud.laz"), out, KinregConfig())
        rows = np.genfromtxt(out / "stations.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
        t = rows["t"].astype(float)
        truth = read_trajectory(data / "truth_trajectory.txt")
        sig = np.column_stack([rows["sx_mm"], rows["sy_mm"], rows["sz_mm"]]) / 1000.0
        free = sig.max(axis=1) > 0
        # The sigmas are relative to the datum (the first station, held at the trajectory's pose,
        # drift included): the truth is moved rigidly onto the pose that station is held at.
        held = t[~free][:1]
        to_datum = read_trajectory(data / "run_trajectory.txt").pose_at(held).compose(truth.pose_at(held).inverse())
        err = np.column_stack([rows["x"], rows["y"], rows["z"]]) - to_datum.apply(truth.pose_at(t).t_xyz)
        z2.append(np.mean((err[free] / sig[free]) ** 2))
    pooled = float(np.sqrt(np.mean(z2)))
    assert 0.7 <= pooled <= 1.5, f"pooled normalised error RMS {pooled:.2f} (per run {np.sqrt(z2).round(2)})"
