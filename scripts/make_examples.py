"""Compute the studio's example results once and cache them in examples/ (the app never runs them).

    python scripts/make_examples.py                 # with the shipped default model
    python scripts/make_examples.py --model DIR     # with another model

The inputs are small scenes rendered here with pyvista (so they ship without licence
questions); each example pairs an input with a bundled probe and a rotation. Rerun this script
whenever the default model changes: it rewrites examples/manifest.json and every result.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

REPO_ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO_ROOT))

import numpy as np  # noqa: E402

from relight_core import lighting, media, outputs  # noqa: E402
from relight_core.pipeline import Relighter, RelightRequest  # noqa: E402

EXAMPLES = [  # name, input, probe, rotation (degrees), video?
    ("Objects under a sunset", "inputs/objects.png", "sunset", 180.0, False),
    ("Objects in a courtyard", "inputs/objects.png", "courtyard", 90.0, False),
    ("Orbit in the studio", "inputs/orbit.mp4", "studio", 180.0, True),
]


def render_scene(azimuth_deg: float, size: tuple[int, int] = (256, 192)) -> np.ndarray:
    """A few coloured objects on a floor, seen from `azimuth_deg`, frames float32 [H,W,3] in [0,1]."""
    import pyvista as pv

    plotter = pv.Plotter(off_screen=True, window_size=size)
    plotter.set_background((0.75, 0.78, 0.82))
    plotter.add_mesh(pv.Plane(center=(0, 0, 0), direction=(0, 1, 0), i_size=6, j_size=6),
                     color=(0.55, 0.5, 0.45))
    plotter.add_mesh(pv.Sphere(radius=0.6, center=(-0.9, 0.6, 0.0)), color=(0.85, 0.25, 0.2),
                     smooth_shading=True, specular=0.4)
    plotter.add_mesh(pv.Cube(center=(0.8, 0.45, -0.4), x_length=0.9, y_length=0.9, z_length=0.9),
                     color=(0.25, 0.45, 0.85))
    plotter.add_mesh(pv.Cylinder(center=(0.2, 0.4, 0.9), direction=(0, 1, 0), radius=0.35, height=0.8),
                     color=(0.9, 0.8, 0.3), smooth_shading=True)
    radius, a = 4.5, np.radians(azimuth_deg)
    plotter.camera_position = [(radius * np.sin(a), 2.2, radius * np.cos(a)), (0, 0.4, 0), (0, 1, 0)]
    plotter.enable_shadows()
    image = plotter.screenshot(return_img=True)
    plotter.close()
    return image[:, :, :3].astype(np.float32) / 255.0


def write_inputs(root: Path) -> None:
    """The example inputs: one still and one short orbiting clip."""
    (root / "inputs").mkdir(parents=True, exist_ok=True)
    media.save_image(root / "inputs/objects.png", render_scene(30.0))
    frames = np.stack([render_scene(a) for a in np.linspace(0.0, 60.0, 17)])
    media.save_video(root / "inputs/orbit.mp4", frames, 12.0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="default", help="'default', a preset name or a model folder")
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "examples")
    parser.add_argument("--steps", type=int, default=None, help="sampling steps (default: the model's)")
    args = parser.parse_args(argv)

    root = args.out
    write_inputs(root)
    relighter = Relighter.load(args.model)
    size = relighter.spec.size
    manifest = {"model": relighter.spec.name, "trained": relighter.spec.trained, "examples": []}
    for index, (name, input_name, probe_name, rotation, video) in enumerate(EXAMPLES):
        loaded = media.load_media(root / input_name)
        frames = media.resize_frames(loaded.frames, size)
        probe = lighting.load_probe(REPO_ROOT / "envmaps" / f"{probe_name}.exr")
        result = relighter.relight(RelightRequest(
            frames=frames, fps=loaded.fps, audio_path=loaded.audio_path, mode="relight", probe=probe,
            rotation=rotation, steps=args.steps, seed=0))
        out_dir = root / "results" / f"{index:02d}"
        # At the input's own resolution, as the studio returns results (guided ratio upsampling).
        clips = outputs.result_clips(result, "relight", frames, full=np.asarray(loaded.frames, dtype=np.float32))
        files = outputs.write_outputs(clips, out_dir, video, result.fps,
                                      result.audio_path, stills=True)
        keys = {"relit_still": "relit_still", "albedo_still": "albedo_still"}
        if video:
            keys |= {"relit_video": "relit", "albedo_video": "albedo"}
        outputs_of = {key: files[name].relative_to(root).as_posix() for key, name in keys.items()}
        downloads = ["relit_video", "albedo_video"] if video else ["relit_still", "albedo_still"]
        manifest["examples"].append({
            "name": name, "input": input_name, "probe": probe_name, "rotation": rotation,
            "mode": "Relight", "video": video, "outputs": outputs_of, "downloads": downloads,
            "seconds": round(result.seconds, 2)})
        print(f"{name}: {result.seconds:.1f} s", flush=True)
    (root / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
