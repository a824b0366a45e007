"""A seed-duration run (266 stations, the seed's walk) at 1/DIV of the seed's point rate."""
import sys, time, json
from dataclasses import replace
from pathlib import Path
sys.path.insert(0, "/work/wt-relink235/benchmarks")
import numpy as np
import bench_scale as bs

def main():
    folder = Path(sys.argv[1]); div = float(sys.argv[2]); workers = int(sys.argv[3])
    folder.mkdir(parents=True, exist_ok=True)
    import laspy
    from kinreg.run.executor import make_executor
    from kinreg.simulation.files import _las_header, write_trajectory_geoslam
    t0 = time.perf_counter()
    config = bs.seed_like_config(235e6)
    config = replace(config, sensor=replace(config.sensor, pulse_rate_hz=config.sensor.pulse_rate_hz / div))
    run = bs._run_of(config)
    write_trajectory_geoslam(folder / "run_trajectory.txt", run.slam)
    n = 0
    with make_executor(workers) as ctx, laspy.open(folder / "run_cloud.laz", mode="w", header=_las_header(run), do_compress=True,
                                                   laz_backend=laspy.LazBackend.LazrsParallel) as writer:
        for stamps, xyz, intensity in ctx.map(bs.simulate_block, ((config, k) for k in range(run.n_blocks()))):
            rec = laspy.ScaleAwarePointRecord.zeros(len(stamps), header=writer.header)
            rec.x, rec.y, rec.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
            rec.gps_time = stamps
            rec.intensity = intensity
            rec.return_number = np.ones(len(stamps), dtype=np.uint8)
            rec.number_of_returns = np.ones(len(stamps), dtype=np.uint8)
            writer.write_points(rec)
            n += len(stamps)
    info = {"points": n, "duration_s": config.duration_s, "div": div, "generate_s": time.perf_counter() - t0}
    (folder / "gen.json").write_text(json.dumps(info))
    print(info)

if __name__ == "__main__":
    main()
