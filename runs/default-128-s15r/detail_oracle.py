"""The share of the shipped model's error that is fine detail, on the validation scenes (QUALITY.md,
top section): its filtered frames with the truth's detail below / content above a Gaussian sigma.
Run from the project root after training.refine has cached the validation outputs (an ad-hoc form
of its refine-val.npz: the pack's scene index, target light and the DiT's frames at gain 1)."""
import numpy as np, torch, cv2
from relight_core.training.pack import load_pack
from relight_core.evaluation.metrics import protocol_psnr
from relight_core.upsample import smooth_offset
C="/root/.cache/unirelight-studio"
pack=load_pack(C+"/s15/val.npz"); z=np.load(C+"/refine-val.npz")
s=torch.from_numpy(z["scene"]); t=torch.from_numpy(z["target"])
hwc=lambda x: x.permute(0,2,3,1).numpy().astype(np.float32)/255
x=hwc(pack["rgb"][s,1-t]); tr=hwc(pack["rgb"][s,t]); ta=hwc(pack["albedo"][s]); m=pack["mask"][s].numpy()
r=z["relit"].transpose(0,2,3,1).astype(np.float32)/255; a=z["albedo"].transpose(0,2,3,1).astype(np.float32)/255
a=np.clip(x+0.95*(a-x),0,1)
fr=smooth_offset(x,r,12); fa=smooth_offset(x,a,4)
def blur(y,sig): return np.stack([cv2.GaussianBlur(i,(0,0),sig) for i in y])
def P(pred,tgt): return np.mean([protocol_psnr(pred[i],tgt[i],m[i]) for i in range(len(m))])
print("mask mean", m.mean())
print("shipped", P(fr,tr), P(fa,ta))
for sig in (1,2,4,8):
    # oracle: keep prediction's high freq, take target's low freq
    lo=np.clip(fr-blur(fr,sig)+blur(tr,sig),0,1); la=np.clip(fa-blur(fa,sig)+blur(ta,sig),0,1)
    # oracle2: prediction's low freq + target's high freq
    hi=np.clip(blur(fr,sig)+tr-blur(tr,sig),0,1); ha=np.clip(blur(fa,sig)+ta-blur(ta,sig),0,1)
    print(sig, "fix low:", round(P(lo,tr),2), round(P(la,ta),2), " fix high:", round(P(hi,tr),2), round(P(ha,ta),2))
