"""Per relink round: how far each station's planes (as linked: deskewed, with the window deformation) and
each pair's prior moved since the round before, against their sigmas."""
import pickle, sys, numpy as np, logging
import kinreg.run.stages as st
from kinreg.geometry import Pose
rounds = []
orig = st.link_stations
def rec(stations, planes, matching, drift, pairwise, progress=None, static=None, executor=None, rates=None,
        adjusted=None, previous=(), loops=True, velocity_cov=None, **kw):
    links = orig(stations, planes, matching, drift, pairwise, progress, static, executor, rates, adjusted, previous, loops, velocity_cov, **kw)
    if adjusted is not None:
        rounds.append((planes, adjusted, links))
    return links
st.link_stations = rec
from kinreg.progress import NullProgress
d = pickle.load(open(sys.argv[1], "rb"))
res = st.adjust_with_measured_drift(d["network"], d["planes"], d["static"], d["config"], NullProgress(), None, d["trajectories"])
for r in range(1, len(rounds)):
    (p0, a0, l0), (p1, a1, l1) = rounds[r - 1], rounds[r]
    # plane moves in sigma units of d and of the normal
    dn, dd = [], []
    for s0, s1 in zip(p0, p1):
        for x, y in zip(s0, s1):
            sd = np.sqrt(x.cov_uvd[2, 2]); sn = np.sqrt(x.cov_uvd[0, 0])
            dd.append(abs((y.normal @ y.centroid_xyz - y.d_m) - (x.normal @ x.centroid_xyz - x.d_m)) / sd + np.linalg.norm(y.centroid_xyz - x.centroid_xyz) * 0 )
            dn.append(np.arccos(min(1.0, float(x.normal @ y.normal))) / sn)
    dd, dn = np.array(dd), np.array(dn)
    cen = np.array([np.linalg.norm(y.centroid_xyz - x.centroid_xyz) for s0, s1 in zip(p0, p1) for x, y in zip(s0, s1)])
    L0 = {(l.scan_i, l.scan_j): l for l in l0}
    moves = []
    for l in l1:
        o = L0.get((l.scan_i, l.scan_j))
        if o is None: continue
        dp = o.T_i_j_prior.inverse().compose(l.T_i_j_prior).log()
        sig = np.sqrt(np.diag(o.cov_xi))
        moves.append(np.max(np.abs(dp) / sig))
        
    moves = np.array(moves)
    dT = []
    for l in l1:
        o = L0.get((l.scan_i, l.scan_j))
        if o is None: continue
        dT.append(1000 * np.linalg.norm(o.T_i_j_planes.inverse().compose(l.T_i_j_planes).t_xyz))
    dT = np.array(dT)
    q = [50, 90, 99, 100]
    print(f"round {r} vs {r-1}: plane centroid moved mm pct {q}: {np.percentile(1000*cen, q).round(4)}")
    print(f"   normal moved / sigma: {np.percentile(dn, q).round(4)}; links' prior moved / link sigma (max axis): {np.percentile(moves, q).round(4)}")
    print(f"   links' plane-only pose moved mm: {np.percentile(dT, q).round(4)}")
