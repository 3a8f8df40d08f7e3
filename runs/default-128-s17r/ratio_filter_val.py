# relit: offset filter (shipped, radius 12) vs a ratio filter on the validation pack
import numpy as np, cv2
from relight_core.training import refine as R
from relight_core.upsample import smooth_offset, GUIDE_EPS
from relight_core.evaluation.metrics import protocol_psnr
from valdata import validation
cv2.setNumThreads(1)
data = validation("raw")
g, o, tgt, m = R._hwc(data["input"]), R._hwc(data["relit"]), R._hwc(data["target"]), data["mask"].numpy()
def score(x): return float(np.mean([protocol_psnr(x[i], tgt[i], m[i]) for i in range(len(m))]))
print("raw", score(o), "offset12", score(smooth_offset(g, o, 12)), flush=True)
def ratio_filter(radius, e, eps=GUIDE_EPS, log=True):
    res = np.empty_like(o)
    for i in range(len(o)):
        gi = np.ascontiguousarray(g[i])
        if log:
            r = np.log(o[i] + e) - np.log(gi + e)
            res[i] = np.clip((gi + e) * np.exp(cv2.ximgproc.guidedFilter(gi, np.ascontiguousarray(r.astype(np.float32)), radius, eps)) - e, 0, 1)
        else:
            r = (o[i] + e) / (gi + e)
            res[i] = np.clip((gi + e) * cv2.ximgproc.guidedFilter(gi, np.ascontiguousarray(r.astype(np.float32)), radius, eps) - e, 0, 1)
    return res
for e in (0.02, 0.05, 0.1, 0.2, 0.4):
    for radius in (4, 6, 8, 12, 16):
        print("ratio log e", e, "r", radius, round(score(ratio_filter(radius, e)), 3), flush=True)
print("offset r8", score(smooth_offset(g, o, 8)), "r6", score(smooth_offset(g, o, 6)))
