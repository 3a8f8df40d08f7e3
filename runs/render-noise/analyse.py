"""How much of the error is the data engine's render noise, and does smoothing the results help? Reads `cache.py`'s
file; every score is the protocol's PSNR (per-channel scale fit on the mask), paired per item against what
`evaluate` reports (the model on the 32-spp input, against the 32-spp target), ± the standard error over scenes.
    PYTHONPATH=. python runs/render-noise/analyse.py CACHE.npz
"""
import sys

import cv2
import numpy as np

from relight_core.evaluation.metrics import protocol_psnr


def main() -> None:
    z = np.load(sys.argv[1])
    scenes = np.array([n.split()[0] for n in z["name"]])

    def score(out, target):
        return np.array([protocol_psnr(out[i][None], target[i][None], z["mask"][i][None]) for i in range(len(out))])

    def line(label, values, base=None):
        text = f"| {label} | {values.mean():.2f} |"
        if base is not None:
            d = values - base
            per = np.array([d[scenes == s].mean() for s in np.unique(scenes)])
            text += f" {d.mean():+.3f} ± {per.std(ddof=1) / np.sqrt(len(per)):.3f} |"
        else:
            text += " |"
        print(text)

    def bilateral(frames, sigma_colour, sigma_space):
        return np.stack([cv2.bilateralFilter(f.astype(np.float32), 5, sigma_colour, sigma_space) for f in frames])

    relit, albedo = score(z["relit"], z["target"]), score(z["albedo"], z["albedo_target"])
    print(f"{len(scenes)} test items (the first {len(np.unique(scenes))} scenes), the shipped model, fp32\n")
    print("| relit | PSNR | paired vs as evaluated |\n|---|---|---|")
    line("as `evaluate` scores it: 32-spp input → 32-spp target", relit)
    line("the same results against the 529-spp target", score(z["relit"], z["clean_target"]), relit)
    line("the model on the 529-spp input → 529-spp target", score(z["relit_clean_in"], z["clean_target"]), relit)
    line("floor: 32-spp input → 32-spp target", score(z["input"], z["target"]))
    line("floor: 529-spp input → 529-spp target", score(z["clean_input"], z["clean_target"]))
    line("the 32-spp target against the 529-spp one (its noise)", score(z["target"], z["clean_target"]))
    line("the results on 32- against 529-spp inputs (noise carried)", score(z["relit"], z["relit_clean_in"]))
    for sc, ss in ((0.03, 1.5), (0.05, 1.5), (0.08, 1.0), (0.12, 1.0)):
        line(f"results smoothed (bilateral 5 px, σ colour {sc}, σ space {ss})",
             score(bilateral(z["relit"], sc, ss), z["target"]), relit)
    print("\n| albedo (its target is the renderer's albedo AOV: no noise) | PSNR | paired vs as evaluated |\n|---|---|---|")
    line("as `evaluate` scores it: 32-spp input", albedo)
    line("the model on the 529-spp input", score(z["albedo_clean_in"], z["albedo_target"]), albedo)
    line("the results on 32- against 529-spp inputs (noise carried)", score(z["albedo"], z["albedo_clean_in"]))
    for sc, ss in ((0.03, 1.5), (0.05, 1.5), (0.08, 1.0)):
        line(f"results smoothed (bilateral 5 px, σ colour {sc}, σ space {ss})",
             score(bilateral(z["albedo"], sc, ss), z["albedo_target"]), albedo)


if __name__ == "__main__":
    main()
