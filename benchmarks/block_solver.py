"""Sparse block solver benchmark: assembly, factorisation, solve and selected inverse.

Run: ``.venv/bin/python benchmarks/block_solver.py [--stations 231 2000 20000 100000]
[--scipy-max 20000] [--out benchmarks/results/block_solver.json]``

Synthetic survey networks: stations 10 m apart along a serpentine path (square-ish: lanes of
about sqrt(n) stations, at least 50, 15 m apart), each station linked to its 4 successors, plus
about 10 loop closures per 100 stations between stations of neighbouring lanes (close in space,
far apart in the sequence), and a prior on the first station (the datum). Each link observes the
relative pose with sigmas of 1 mm (translation) and 0.1 mrad (rotation); its linearised Jacobians
couple rotation and translation through the lever arm between the stations, as a real
relative-pose link does.

Per network and backend: the time to assemble ``N`` and ``b`` from the per-link 12 x 12
contributions (vectorised COO), to factorise, to solve, and to compute the selected inverse
(diagonal blocks + all link pairs). With ``--check`` (up to 2,000 stations) the covariances are
compared with the dense inverse. Each network runs in a child process of its own, so that its
peak resident memory (``peak_rss_gb``, from ``getrusage``) is its own.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from kinreg.estimate.sparse import factorize, selected_inverse

SIGMA_T_M = 1e-3
SIGMA_R_RAD = 1e-4


def _skew(v: np.ndarray) -> np.ndarray:
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def network(n_stations: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Station positions (n, 3) in metres, links (m, 2) and per-link 12 x 12 information blocks."""
    rng = np.random.default_rng(seed)
    lane_length = max(50, round(np.sqrt(n_stations)))  # stations per lane of the serpentine path
    k = np.arange(n_stations)
    lane, along = divmod(k, lane_length)
    x = np.where(lane % 2 == 0, along, lane_length - 1 - along) * 10.0
    xyz = np.column_stack([x, lane * 15.0, rng.normal(0, 0.5, n_stations)])
    chain = np.array([(i, i + s) for i in range(n_stations) for s in range(1, 5) if i + s < n_stations])
    # Loop closures: a random station and one of the nearest stations of the next lane.
    n_closures = max(1, n_stations // 10) if n_stations > lane_length else 0
    i = rng.choice(n_stations - lane_length, n_closures, replace=False) if n_closures else np.zeros(0, int)
    lane_i, along_i = divmod(i, lane_length)
    j = (lane_i + 1) * lane_length + (lane_length - 1 - along_i) + rng.integers(-2, 3, len(i))
    j = np.clip(j, (lane_i + 1) * lane_length, np.minimum((lane_i + 2) * lane_length, n_stations) - 1)
    links = np.unique(np.concatenate([chain, np.column_stack([i, j])]), axis=0)
    links = links[links[:, 0] != links[:, 1]]
    # Relative pose e = x_j - A x_i with A = [[I, -[d]x], [0, I]] (d: lever arm from i to j).
    d = xyz[links[:, 1]] - xyz[links[:, 0]]
    A = np.tile(np.eye(6), (len(links), 1, 1))
    A[:, :3, 3:] = -_skew(d)
    J = np.concatenate([-A, np.tile(np.eye(6), (len(links), 1, 1))], axis=2)  # (m, 6, 12)
    w = 1.0 / np.array([SIGMA_T_M] * 3 + [SIGMA_R_RAD] * 3) ** 2
    info = J.swapaxes(1, 2) @ (w[:, None] * J)  # (m, 12, 12)
    return xyz, links, info


def assemble(n_stations: int, links: np.ndarray, info: np.ndarray,
             residual: np.ndarray) -> tuple[sp.csc_matrix, np.ndarray]:
    """``N`` (6n x 6n, csc) and ``b`` from per-link (12 x 12) blocks and (12,) gradients, plus a prior."""
    idx = (6 * links[:, :, None] + np.arange(6)).reshape(len(links), 12)  # (m, 12) unknown indices
    rows = np.broadcast_to(idx[:, :, None], info.shape).ravel()
    cols = np.broadcast_to(idx[:, None, :], info.shape).ravel()
    prior = np.diag(1.0 / np.array([SIGMA_T_M] * 3 + [SIGMA_R_RAD] * 3) ** 2)
    r0, c0 = np.nonzero(prior)
    n = 6 * n_stations
    N = sp.csc_matrix((np.concatenate([info.ravel(), prior[r0, c0]]),
                       (np.concatenate([rows, r0]), np.concatenate([cols, c0]))), shape=(n, n))
    b = np.bincount(idx.ravel(), weights=residual.ravel(), minlength=n)
    return N, b


def run(n_stations: int, backend: str, check: bool) -> dict:
    _, links, info = network(n_stations)
    residual = np.random.default_rng(1).normal(size=(len(links), 12))
    t0 = time.perf_counter()
    N, b = assemble(n_stations, links, info, residual)
    t1 = time.perf_counter()
    factor = factorize(N, backend=backend)
    t2 = time.perf_counter()
    x = factor.solve(b)
    t3 = time.perf_counter()
    diag, pair = selected_inverse(N, 6, links, factor=factor)
    t4 = time.perf_counter()
    L, _, _ = factor.lower()
    out = {
        "stations": n_stations, "backend": backend, "unknowns": 6 * n_stations, "links": len(links),
        "nnz_N": int(N.nnz), "nnz_L": int(L.nnz),
        "assembly_s": t1 - t0, "factor_s": t2 - t1, "solve_s": t3 - t2, "selected_inverse_s": t4 - t3,
        "total_s": t4 - t0,
        "residual_rel": float(np.linalg.norm(N @ x - b) / np.linalg.norm(b)),
        "sigma_last_station_mm": float(1e3 * np.sqrt(np.trace(diag[-1, :3, :3]) / 3)),
        "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6,
    }
    if check:
        # Jacobi scaling first: mm and 0.1 mrad unknowns differ by 1e2 in scale, the plain inverse
        # would lose two digits of the reference.
        scale = 1.0 / np.sqrt(N.diagonal())
        Z = scale[:, None] * np.linalg.inv(scale[:, None] * N.toarray() * scale) * scale
        ref = Z.reshape(n_stations, 6, n_stations, 6)
        ref_diag = ref[np.arange(n_stations), :, np.arange(n_stations), :]
        ref_pair = ref[links[:, 0], :, links[:, 1], :]
        out["max_rel_error_diag"] = float(np.abs(diag - ref_diag).max() / np.abs(ref_diag).max())
        out["max_rel_error_pairs"] = float(np.abs(pair - ref_pair).max() / np.abs(ref_pair).max())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stations", type=int, nargs="+", default=[231, 2000, 20000, 100000])
    parser.add_argument("--scipy-max", type=int, default=20000, help="largest network for the scipy backend")
    parser.add_argument("--check", action="store_true", help="compare with the dense inverse (<= 2,000)")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "block_solver.json")
    parser.add_argument("--one", nargs=3, metavar=("STATIONS", "BACKEND", "CHECK"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(run(int(args.one[0]), args.one[1], args.one[2] == "1")))
        return
    results = []
    for n in args.stations:
        for backend in ("cholmod", "scipy"):
            if backend == "scipy" and n > args.scipy_max:
                continue
            child = [sys.executable, __file__, "--one", str(n), backend, str(int(args.check and n <= 2000))]
            res = json.loads(subprocess.run(child, check=True, capture_output=True, text=True).stdout)
            results.append(res)
            print(json.dumps(res))
    meta = {"date": time.strftime("%Y-%m-%d"), "python": platform.python_version(),
            "machine": platform.machine(), "cpus": os.cpu_count(),
            "OMP/OPENBLAS threads": os.environ.get("OPENBLAS_NUM_THREADS", "default"),
            "command": " ".join(sys.argv)}
    args.out.write_text(json.dumps({"meta": meta, "results": results}, indent=1) + "\n")


if __name__ == "__main__":
    main()
