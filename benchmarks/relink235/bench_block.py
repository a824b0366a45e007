"""Time (wall, CPU) adjust_with_measured_drift on captured inputs; optionally profile; save outputs.
usage: bench_block.py CAPTURE.pkl OUT.npz [--profile PROF] [--workers N]"""
import argparse, pickle, sys, time, logging, json
import numpy as np

def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("capture"); ap.add_argument("out")
    ap.add_argument("--profile"); ap.add_argument("--workers", type=int, default=1)
    a = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(relativeCreated)8.0f %(name)s %(message)s", stream=sys.stderr)
    from kinreg.progress import NullProgress
    from kinreg.run.executor import make_executor
    from kinreg.run.stages import adjust_with_measured_drift
    d = pickle.load(open(a.capture, "rb"))
    with make_executor(a.workers) as ex:
        w, c = time.perf_counter(), time.process_time()
        if a.profile:
            import cProfile
            pr = cProfile.Profile(time.process_time)
            pr.enable()
        res = adjust_with_measured_drift(d["network"], d["planes"], d["static"], d["config"], NullProgress(), ex,
                                         d["trajectories"])
        if a.profile:
            pr.disable(); pr.dump_stats(a.profile)
        wall, cpu = time.perf_counter() - w, time.process_time() - c
        import psutil
        kids = psutil.Process().children(recursive=True)
        workers_cpu = sum(k.cpu_times().user + k.cpu_times().system for k in kids)
    r = res.result
    links = res.network.links
    np.savez(a.out, poses_t=r.poses.t_xyz, poses_q=r.poses.quat_wxyz, cov=r.cov_xi, sigma0=r.sigma0,
             pairs=np.array([(l.scan_i, l.scan_j) for l in links]),
             status=np.array([l.status.value for l in links]),
             T_planes_t=np.array([l.T_i_j_planes.t_xyz for l in links]),
             T_planes_q=np.array([l.T_i_j_planes.quat_wxyz for l in links]),
             T_t=np.array([l.T_i_j.t_xyz for l in links]), T_q=np.array([l.T_i_j.quat_wxyz for l in links]), Tp_q=np.array([l.T_i_j_planes.quat_wxyz for l in links]), info=np.array([l.info_planes for l in links]),
             nmatch=np.array([len(l.matches) for l in links]),
             rates=np.concatenate([res.rates.pos_m_per_s, res.rates.rot_rad_per_s, [res.rates.coupling]]))
    import os
    print(json.dumps({"wall_s": wall, "cpu_s": cpu, "workers_cpu_s": workers_cpu, "load": os.getloadavg(), "n_links": len(links), "sigma0": float(r.sigma0),
                      "coupling": float(res.rates.coupling)}))

if __name__ == "__main__":
    main()
