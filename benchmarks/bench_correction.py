"""Time of the per-point drift correction (``DriftCorrection.apply_to_points``) on 2 M points of the
sample trajectory with random station corrections. ``python benchmarks/bench_correction.py ref``
keeps the result as the reference in /tmp; a later run prints its difference from it (mm)."""

import time

import numpy as np

from kinreg.estimate.correction import DriftCorrection
from kinreg.geometry import Pose, rotvec_to_quat
from kinreg.io.trajectory import read_trajectory

traj = read_trajectory("sample_data/run_trajectory.txt")
rng = np.random.default_rng(0)
ts = np.linspace(traj.t_start_s + 3, traj.t_end_s - 3, 40)
init = traj.pose_at(ts)
adj = Pose(rotvec_to_quat(rng.normal(0, 0.003, (40, 3))), rng.normal(0, 0.05, (40, 3))).compose(init)
c = DriftCorrection.from_stations(ts, init, adj, traj)
n = 2_000_000
t = np.sort(rng.uniform(traj.t_start_s, traj.t_end_s, n))
xyz = traj.pose_at(t).t_xyz + rng.normal(0, 8, (n, 3)) + np.array([500000.0, 5400000.0, 300.0]) * 0
t0 = time.perf_counter(); a = c.apply_to_points(xyz, t); t1 = time.perf_counter()
print("apply_to_points %.3f s for %d points" % (t1 - t0, n))
np.save("/tmp/corr_ref.npy", a) if __import__("sys").argv[-1] == "ref" else print("max diff mm", np.abs(a - np.load("/tmp/corr_ref.npy")).max() * 1000)
ref = np.load("/tmp/corr_ref.npy"); e = np.abs(a - ref).max(axis=1); k = int(np.argmax(e))
print("worst at t-rel", t[k] - traj.t_start_s, "stations", ts[0] - traj.t_start_s, ts[-1] - traj.t_start_s, "dist", np.linalg.norm(xyz[k] - traj.pose_at(t[k]).t_xyz))
print("p99 diff mm", np.percentile(e, 99) * 1000)
