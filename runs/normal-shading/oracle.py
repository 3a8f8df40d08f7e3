"""How much of the relit target a diffuse shading model explains, knowing the true normals: for test scenes,
render the camera-frame shading normals (Mitsuba's sh_normal AOV), compute the irradiance E(n) of the target's
camera-frame probe (cosine lobe over the panorama), and score albedo_GT · E_B(n) and input · E_B(n)/E_A(n)
against the target under the protocol (per-channel scale fit on the mask).
    PYTHONPATH=. python runs/normal-shading/oracle.py DATA_ROOT SCENES [EVAL_DIR]
"""
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from relight_core.colour import linear_to_srgb, srgb_to_linear
from relight_core.data.files import read_exr
from relight_core.data.generate import frame_seed
from relight_core.data.render import SceneRenderer
from relight_core.data.scenes import camera_to_world, sample_scene
from relight_core.evaluation.metrics import protocol_psnr
from relight_core.lighting.panorama import panorama_directions


def png(path):
    return cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGR2RGB).astype(np.float32) / 255


def normals(spec, size):
    import mitsuba as mi
    with SceneRenderer(spec, size, 16) as r:
        scene = r.scene_dict(0, 0)
        scene["integrator"] = {"type": "aov", "aovs": "nn:sh_normal"}
        n = np.asarray(mi.render(mi.load_dict(scene), spp=16, seed=frame_seed(spec, 0)), np.float32)[..., :3]
    n = n @ camera_to_world(spec, 0)          # world → camera: R^T n, as row vectors n R
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6)
    n *= np.where(n[..., 2:3] < 0, -1, 1)      # two-sided: face the camera
    return n


def irradiance(env, n):
    """Cosine-weighted sum of the camera-frame panorama env [h,w,3] over directions, per normal n [H,W,3]."""
    h, w, _ = env.shape
    d = panorama_directions(h, w).numpy().reshape(-1, 3)
    sin = np.sqrt(np.clip(1 - d[:, 1] ** 2, 0, 1))
    L = env.reshape(-1, 3) * sin[:, None]
    cos = np.clip(n.reshape(-1, 3) @ d.T, 0, None)        # [HW, hw]
    return (cos @ L).reshape(*n.shape[:2], 3) / sin.sum()


def sh_basis(n):
    """The 9 real spherical harmonics (bands 0–2, unnormalised) of unit normals n [...,3]."""
    x, y, z = n[..., 0], n[..., 1], n[..., 2]
    return np.stack([np.ones_like(x), x, y, z, x * y, y * z, x * z, x * x - y * y, 3 * z * z - 1], -1)


def fit_irradiance(shading, n, mask):
    """Per channel the least-squares SH-9 fit of `shading` [H,W,3] over the mask's pixels, evaluated at n."""
    B = sh_basis(n)
    sel = mask > 0
    coef, *_ = np.linalg.lstsq(B[sel], shading[sel], rcond=None)
    return B @ coef


def score(pred_lin, target, mask):
    return protocol_psnr(linear_to_srgb(np.clip(pred_lin / np.percentile(pred_lin[mask > 0], 99), 0, 1)), target, mask)


root, count = Path(sys.argv[1]), int(sys.argv[2])
shipped = {}
if len(sys.argv) > 3:
    for it in json.load(open(f"{sys.argv[3]}/metrics.json"))["test"]["per_item"]:
        shipped[it["name"]] = (it["model"]["relit"]["psnr"], it["floor"]["relit"]["psnr"])
rows = []
for i in range(count):
    folder = root / "test" / f"scene_{i:06d}"
    spec = sample_scene(0, "test", i, 1)
    n = normals(spec, 128)
    mask = png(folder / "mask/0000.png")
    mask = mask[..., 0] if mask.ndim == 3 else mask
    albedo = srgb_to_linear(png(folder / "albedo/0000.png"))
    rgb = [png(folder / f"rgb{k}/0000.png") for k in (0, 1)]
    E = [irradiance(read_exr(folder / f"env{k}/0000.exr")[..., :3], n) for k in (0, 1)]
    for a, b in ((0, 1), (1, 0)):
        name = f"scene_{i:06d} {a}→{b}"
        phys = score(albedo * E[b], rgb[b], mask)
        ratio = score(srgb_to_linear(rgb[a]) * E[b] / np.maximum(E[a], 1e-6), rgb[b], mask)
        S_A = srgb_to_linear(rgb[a]) / np.maximum(albedo, 0.02)
        fit = score(srgb_to_linear(rgb[a]) * E[b] / np.maximum(fit_irradiance(S_A, n, mask), 1e-3 * E[b].mean()),
                    rgb[b], mask)
        rows.append((phys, ratio, fit, *shipped.get(name, (np.nan, np.nan))))
        print(name, " ".join(f"{x:6.2f}" for x in rows[-1]), flush=True)
rows = np.array(rows)
print("mean: albedo·E_B %.2f   input·E_B/E_A %.2f   input·E_B/fit %.2f   shipped %.2f   floor %.2f" % tuple(np.nanmean(rows, 0)))

if len(sys.argv) > 4:   # a picture of the last scene: target B | albedo·E_B | input·E_B/E_A | normals
    pred = albedo * E[1]
    pred = linear_to_srgb(np.clip(pred / np.percentile(pred[mask > 0], 99), 0, 1))
    ratio = srgb_to_linear(rgb[0]) * E[1] / np.maximum(E[0], 1e-6)
    ratio = linear_to_srgb(np.clip(ratio / np.percentile(ratio[mask > 0], 99), 0, 1))
    row = np.concatenate([rgb[0], rgb[1], pred, ratio, n * 0.5 + 0.5], 1)
    cv2.imwrite(sys.argv[4], cv2.cvtColor((row * 255).astype(np.uint8), cv2.COLOR_RGB2BGR))
