"""Run one eval case (medium class) and, from its last block adjustment, Förstner's ratio vtpv / r of
the scan planes' kinds split by their physical plane's orientation: level (|n_z| > 0.9), vertical
(|n_z| < 0.3), oblique. A subgroup whose ratio is far from its kind's shares a variance component
with observations of another precision.

usage: python benchmarks/vc_subgroups.py SCENARIO DRIFT_MODEL SEED
"""
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
import eval_accuracy as ea
import numpy as np

import kinreg.estimate.frames as fr

last = {}
orig = fr.adjust_block


def cap(*a, **k):
    r = orig(*a, **k)
    last["a"], last["r"] = a, r
    return r


fr.adjust_block = cap
sc, model, seed = sys.argv[1], sys.argv[2], int(sys.argv[3])
with tempfile.TemporaryDirectory() as tmp:
    res = ea.evaluate(sc, Path(tmp), seed, None, model, "medium")
components = {k: round(v, 3) for k, v in res["variance_components"].items() if "plane" in k}
print(sc, model, seed, "z ratio", round(res["normalised_error_rms_per_axis"][2], 2), "components", components)
result = last["r"]
groups: dict[tuple[str, str], list[float]] = {}
for t in result.tests:
    if "plane" not in t.kind.value or not np.isfinite(t.vtpv) or t.j >= len(result.poses):
        continue
    nz = abs(result.poses[t.j].rotation_matrix[2, 2])  # the node's z axis is its plane's normal
    group = groups.setdefault((t.kind.value, "level" if nz > 0.9 else "vertical" if nz < 0.3 else "oblique"), [0, 0, 0])
    group[0] += t.vtpv
    group[1] += t.redundancy
    group[2] += 1
for (kind, orientation), (vtpv, r, n) in sorted(groups.items()):
    print(f"  {kind:22s} {orientation:9s} n={n:4d}  vtpv/r = {vtpv / r if r > 0 else float('nan'):.3f}")
