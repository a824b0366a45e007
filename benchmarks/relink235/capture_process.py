"""kinreg process on DIR/run_*.{txt,laz} into OUT with adjust_or_fail's inputs pickled to CAPTURE."""
from pathlib import Path
import os, pickle, sys, time, logging, json
import kinreg.run.pipeline as pl
from kinreg.config import load_config

orig = pl.adjust_or_fail
def wrapped(network, planes, static, config, progress, executor, folder, report_inputs, trajectories=()):
    with open(os.environ["CAPTURE"], "wb") as f:
        pickle.dump({"network": network, "planes": planes, "static": static, "config": config,
                     "trajectories": trajectories}, f)
    w, c = time.perf_counter(), time.process_time()
    out = orig(network, planes, static, config, progress, executor, folder, report_inputs, trajectories)
    print(f"ADJUST wall {time.perf_counter() - w:.2f} s cpu {time.process_time() - c:.2f} s", file=sys.stderr, flush=True)
    return out
if __name__ == '__main__':
    pl.adjust_or_fail = wrapped
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s", stream=sys.stderr)
    d, out = sys.argv[1], sys.argv[2]
    t = time.perf_counter()
    s = pl.process(pl.ProcessInputs(Path(f"{d}/run_trajectory.txt"), Path(f"{d}/run_cloud.laz")), out, load_config(None),
                   overwrite=True, workers=None)
    print(json.dumps({"wall_s": time.perf_counter() - t, "timings_s": s.timings_s}))
