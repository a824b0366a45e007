"""``adjust_block`` of two source trees on the test suite's networks: same decisions, same figures?

The networks of ``tests/test_block.py`` (a ring of 60 stations, rank-5 plane links, loop
closures; four seeds, two with a 2 cm gross error; each with the default config and without
variance components and snooping) and of ``tests/test_block_normal.py`` (drift velocities,
a station observation, a control point; three seeds). Each tree adjusts them in a child process;
the script prints whether the rejections, global tests and iterations agree and the largest
relative differences of sigma0, the station covariances, the statistics and the redundancies.

Usage: python benchmarks/compare_block.py --trees /tmp/main-tree . [--out benchmarks/compare_block.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pickle
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def make_networks(path: Path) -> None:
    sys.path[:0] = [str(REPO), str(REPO / "tests")]  # this tree's kinreg and tests build the networks
    from test_block import network
    from test_block_normal import _every_kind

    from kinreg.config import BlockConfig
    from kinreg.geometry import Pose

    nets = {}
    for seed in range(4):
        truth, approx, obs = network(np.random.default_rng(seed))
        obs = list(obs)
        if seed % 2:
            obs[20] = dataclasses.replace(obs[20], Z=obs[20].Z.compose(Pose.exp(np.array([0.02, 0, 0, 0, 0, 0]))))
        fixed = np.zeros(len(truth), bool)
        fixed[0] = True
        nets[f"ring{seed}"] = (approx, obs, fixed, BlockConfig())
        nets[f"ring{seed}_plain"] = (approx, obs, fixed, BlockConfig(variance_components=False, data_snooping=False))
    for seed in range(3):
        truth, approx, obs = _every_kind(np.random.default_rng(100 + seed))
        fixed = np.zeros(len(truth), bool)
        fixed[0] = True
        nets[f"every_kind{seed}"] = (approx, obs, fixed, BlockConfig())
    path.write_bytes(pickle.dumps(nets))


def adjust_all(networks: Path, out: Path) -> None:
    from kinreg.estimate.block import adjust_block

    results = {}
    for name, (approx, obs, fixed, cfg) in pickle.loads(networks.read_bytes()).items():
        r = adjust_block(approx, obs, fixed, cfg)
        results[name] = dict(
            sigma0=r.sigma0, t=r.poses.t_xyz, cov=r.cov_xi, passed=r.global_test_passed, it=r.iterations,
            vc=r.variance_components, stat=np.array([t.statistic for t in r.tests]),
            norm=np.array([t.normalised for t in r.tests]), red=np.array([t.redundancy for t in r.tests]),
            least=np.array([t.min_redundancy for t in r.tests]), rej=np.array([t.rejected for t in r.tests]),
            idx=np.array([t.index for t in r.tests]))
    out.write_bytes(pickle.dumps(results))


def compare(a: dict, b: dict) -> dict:
    same = all(np.array_equal(a[n][k], b[n][k]) for n in b for k in ("rej", "idx", "passed", "it"))
    worst: dict[str, float] = {}

    def note(key: str, value: float) -> None:
        worst[key] = max(worst.get(key, 0.0), float(value))

    for n in b:
        x, y = a[n], b[n]
        note("sigma0", abs(x["sigma0"] - y["sigma0"]) / y["sigma0"])
        note("variance_components", max(abs(x["vc"][k] - y["vc"][k]) / y["vc"][k] for k in y["vc"]))
        note("positions_m", np.abs(x["t"] - y["t"]).max())
        scale = np.abs(y["cov"]).max(axis=(1, 2), keepdims=True)
        ok = scale[:, 0, 0] > 0
        note("cov_per_station", (np.abs(x["cov"] - y["cov"])[ok] / scale[ok]).max())
        for k in ("stat", "norm", "red", "least"):
            m = np.isfinite(y[k])
            if not np.array_equal(np.isfinite(x[k]), m):
                same = False
            if m.any():
                note(k, (np.abs(x[k][m] - y[k][m]) / np.maximum(np.abs(y[k][m]), 1e-9)).max())
    return {"networks": len(b), "same_decisions": bool(same), "largest_relative_difference": worst}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trees", type=Path, nargs=2, required=True, help="the tree under test, the reference")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--adjust", nargs=2, type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.adjust:
        adjust_all(*args.adjust)
        return
    with tempfile.TemporaryDirectory() as tmp:
        networks = Path(tmp) / "networks.pkl"
        make_networks(networks)
        results = []
        for k, tree in enumerate(args.trees):
            out = Path(tmp) / f"result{k}.pkl"
            env = dict(os.environ, PYTHONPATH=str(tree.resolve()))
            subprocess.run([sys.executable, str(Path(__file__).resolve()), "--trees", *map(str, args.trees),
                            "--adjust", str(networks), str(out)], check=True, env=env, cwd=tree)
            results.append(pickle.loads(out.read_bytes()))
    summary = {"trees": [str(t) for t in args.trees], **compare(*results)}
    print(json.dumps(summary, indent=1))
    if args.out:
        args.out.write_text(json.dumps(summary, indent=1) + "\n")


if __name__ == "__main__":
    main()
