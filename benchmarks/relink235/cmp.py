import sys, numpy as np
a, b = np.load(sys.argv[1]), np.load(sys.argv[2])
print("pairs same:", a["pairs"].shape == b["pairs"].shape and (a["pairs"] == b["pairs"]).all(),
      "status same:", (a["status"] == b["status"]).all() if a["status"].shape == b["status"].shape else False,
      "nmatch same:", (a["nmatch"] == b["nmatch"]).all() if a["nmatch"].shape == b["nmatch"].shape else False)
print("station pos max diff mm: %.3g" % (1000 * np.abs(a["poses_t"] - b["poses_t"]).max()))
print("station quat max diff: %.3g" % np.abs(a["poses_q"] - b["poses_q"]).max())
sa = np.sqrt(np.diagonal(a["cov"], axis1=1, axis2=2)); sb = np.sqrt(np.diagonal(b["cov"], axis1=1, axis2=2))
print("station sigma max rel diff: %.3g" % np.nanmax(np.abs(sa - sb) / np.maximum(sa, 1e-300)))
print("sigma0 %.10g %.10g" % (a["sigma0"], b["sigma0"]), "rates rel diff %.3g" % np.max(np.abs(a["rates"] - b["rates"]) / np.maximum(np.abs(a["rates"]), 1e-300)))
if a["pairs"].shape == b["pairs"].shape and (a["pairs"] == b["pairs"]).all():
    print("link T_planes max diff mm: %.3g" % (1000 * np.abs(a["T_planes_t"] - b["T_planes_t"]).max()),
          "link T max diff mm: %.3g" % (1000 * np.abs(a["T_t"] - b["T_t"]).max()),
          "info max rel: %.3g" % (np.abs(a["info"] - b["info"]).max() / np.abs(a["info"]).max()))
