"""Mitsuba 3 rendering of a `SceneSpec`: RGB under two probes, albedo AOV, mask, camera-frame probes.

Conventions:
* Mitsuba's `envmap` looks a direction up at `u = atan2(x, −z)/2π` (no +0.5), 180° of yaw away
  from the project's `u = 0.5 + atan2(x, −z)/2π`; `to_mitsuba_bitmap` rolls the map by half its
  width so both read the same radiance for every world direction (tests/test_data_render.py).
* `max_depth = 3` in Mitsuba counts path segments: camera → surface → surface → light, i.e.
  direct light plus one indirect bounce — the paper's "path length three".
* The camera frame is x right, y up, looking down −Z; the probe handed to the model is the full
  panorama `lighting.probe_in_camera` builds from the world probe, the probe's yaw and the
  frame's camera rotation.
"""

from __future__ import annotations

import glob
import math
import os
import tempfile
import warnings

import cv2
import numpy as np
import torch

from relight_core import lighting
from relight_core.colour import srgb_to_linear
from relight_core.data import probes as probe_lib
from relight_core.data.meshes import build_mesh, write_ply
from relight_core.data.scenes import (GROUND_SIZE, MaterialSpec, SceneSpec, camera_position,
                                      camera_to_world, object_pose, probe_yaw)
from relight_core.data.textures import make_texture
from relight_core.errors import InputError

_variant: str | None = None
TEXTURE_SIZE = 256
PROBE_HEIGHT = 128  # procedural probes are generated at 128×256
AOV_SPP = 16  # albedo/mask samples per pixel (anti-aliasing only: no noise to average out)


CPU_VARIANT, CUDA_VARIANT = "llvm_ad_rgb", "cuda_ad_rgb"
RENDER_DEVICES = ("auto", "cpu", "cuda")


def _find_llvm() -> None:
    if "DRJIT_LIBLLVM_PATH" not in os.environ:
        found = sorted(glob.glob("/usr/lib/*/libLLVM-19.so*") + glob.glob("/usr/lib/*/libLLVM.so.19*"))
        if found:
            os.environ["DRJIT_LIBLLVM_PATH"] = found[0]


def _cuda_problem() -> str | None:
    """Why Mitsuba's CUDA variant cannot render in this process (None when it can): it is selected and a
    two-pixel scene rendered, so a missing GPU, driver or OptiX shows here rather than in every scene."""
    import mitsuba as mi

    if CUDA_VARIANT not in mi.variants():
        return f"this Mitsuba build has no {CUDA_VARIANT} variant"
    before = mi.variant()
    try:
        mi.set_variant(CUDA_VARIANT)
        scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 3},
                              "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 2, "height": 1}},
                              "shape": {"type": "sphere", "to_world": mi.ScalarTransform4f().translate([0, 0, 3])},
                              "light": {"type": "constant"}})
        np.asarray(mi.render(scene, spp=1))
        return None
    except Exception as err:  # no GPU, no driver, no OptiX: the reason, in Dr.Jit's words
        text = " ".join(str(err).split())
        if "CUDA backend hasn't been initialized" in text:  # what Dr.Jit says where it finds no CUDA driver
            return "Dr.Jit finds no CUDA driver or GPU"
        return text[:200] or type(err).__name__
    finally:
        if before is not None and before != CUDA_VARIANT:
            mi.set_variant(before)


def render_device(device: str | None = "auto", why_not: list[str] | None = None) -> str:
    """The device `render-data` renders on: "cuda" (Mitsuba's cuda_ad_rgb) when asked for or, for "auto", when
    it renders here; else "cpu" (llvm_ad_rgb). Asking for "cuda" where it cannot render is an InputError;
    "auto" that falls back to the CPU appends the reason to `why_not`."""
    device = device or "auto"
    if device not in RENDER_DEVICES:
        raise InputError(f"--device {device} is not one of {', '.join(RENDER_DEVICES)}.")
    if device == "cpu":
        return "cpu"
    problem = _cuda_problem()
    if problem is None:
        return "cuda"
    if device == "cuda":
        raise InputError(f"Mitsuba cannot render on a CUDA GPU here ({problem}); render with --device cpu, "
                         "or run on a machine with an NVIDIA GPU and its driver.")
    if why_not is not None:
        why_not.append(problem)
    return "cpu"


def init_mitsuba(threads: int | None = None, device: str = "cpu") -> str:
    """Select the process's Mitsuba variant for `device` ("cpu": llvm_ad_rgb, else scalar_rgb with a warning;
    "cuda": cuda_ad_rgb) and return it. A process keeps the variant it first selected for a device."""
    global _variant
    import drjit as dr
    import mitsuba as mi

    if device == "cuda":
        if _variant != CUDA_VARIANT:
            mi.set_variant(CUDA_VARIANT)
            _variant = mi.variant()
        return _variant
    if _variant is None or _variant == CUDA_VARIANT:
        _find_llvm()
        try:
            mi.set_variant(CPU_VARIANT)
        except (ImportError, AttributeError, RuntimeError) as err:
            warnings.warn(f"Mitsuba's {CPU_VARIANT} variant is unavailable ({err}); rendering with the "
                          "~3x slower scalar_rgb. Install libllvm19 to fix.", RuntimeWarning, stacklevel=2)
            mi.set_variant("scalar_rgb")
        _variant = mi.variant()
    if threads is not None:
        # One thread per process keeps the film accumulation order, hence the bits, reproducible.
        dr.set_thread_count(threads)
    return _variant


def stratified_spp(spp: int) -> int:
    """Samples per pixel rounded up to a square: the multijitter sampler stratifies k×k exactly."""
    k = math.isqrt(spp - 1) + 1 if spp > 1 else 1
    return k * k


def to_mitsuba_bitmap(probe: np.ndarray) -> np.ndarray:
    """Project-convention lat-long [h,w,3] → the array Mitsuba's envmap reads the same way."""
    return np.roll(probe, -probe.shape[1] // 2, axis=1)


class SceneRenderer:
    """Renders one `SceneSpec` frame by frame; owns its meshes, textures and probes."""

    def __init__(self, spec: SceneSpec, size: int, spp: int, probes: list[np.ndarray] | None = None):
        """`probes` overrides the two world probes of `spec.probes` (lat-long, project convention)."""
        init_mitsuba()
        import mitsuba as mi

        self.spec, self.size, self.spp = spec, size, stratified_spp(spp)
        self._tmp = tempfile.TemporaryDirectory(prefix="relight-meshes-")
        self._mesh_files: list[str | None] = []
        for i, obj in enumerate(spec.objects):
            if obj.shape in ("cube", "sphere"):
                self._mesh_files.append(None)
            else:
                path = os.path.join(self._tmp.name, f"object{i}.ply")
                write_ply(path, build_mesh(obj.shape, obj.shape_seed))
                self._mesh_files.append(path)
        # Texture bitmaps of the ground (index 0) and of each object (index i + 1).
        self._textures = [
            None if mat.texture is None
            else mi.Bitmap(srgb_to_linear(make_texture(mat.texture, TEXTURE_SIZE)).astype(np.float32))
            for mat in [spec.ground] + [o.material for o in spec.objects]
        ]
        if probes is None:
            probes = [probe_lib.load_choice(choice, PROBE_HEIGHT) for choice in spec.probes]
        self.probes = [np.asarray(p, np.float32) for p in probes]
        self._bitmaps = [mi.Bitmap(to_mitsuba_bitmap(p).astype(np.float32)) for p in self.probes]

    def close(self) -> None:
        """Remove the temporary mesh files."""
        self._tmp.cleanup()

    def __enter__(self) -> SceneRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def render(self, frame: int, light: int, seed: int) -> np.ndarray:
        """Path-trace one frame under probe `light`: linear RGB [H,W,3]."""
        import mitsuba as mi

        scene = mi.load_dict(self.scene_dict(frame, light))
        return np.clip(np.asarray(mi.render(scene, spp=self.spp, seed=seed), dtype=np.float32), 0, None)

    def render_aovs(self, frame: int, seed: int, light: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Albedo (linear [H,W,3]) and mask ([H,W] in {0,1}) of a frame; they do not depend on `light`.

        A separate AOV-only pass: wrapping the path tracer in the `aov` integrator doubles its cost,
        and anti-aliasing the albedo needs far fewer samples than the light transport.
        """
        import mitsuba as mi

        scene = self.scene_dict(frame, light)
        scene["integrator"] = {"type": "aov", "aovs": "albedo:albedo,depth:depth"}
        image = np.asarray(mi.render(mi.load_dict(scene), spp=min(self.spp, AOV_SPP), seed=seed), np.float32)
        return np.clip(image[..., 0:3], 0, 1), (image[..., 3] > 0).astype(np.float32)

    def camera_probe(self, frame: int, light: int) -> np.ndarray:
        """The probe as seen from this frame's camera: panorama [H,W,3] in the model's convention."""
        probe = self.probes[light]
        h, w = self.size, self.size
        # Area-average to twice the panorama's width first so a small sun cannot alias away.
        target_w = 2 * w
        if probe.shape[1] > target_w:
            probe = cv2.resize(probe, (target_w, target_w // 2), interpolation=cv2.INTER_AREA)
        # World radiance L(d) = file(R_y(−yaw)·d) (the envmap's to_world is R_y(yaw)), so the camera
        # panorama pixel e holds file(R_y(−yaw)·c2w·e): probe_in_camera with rotation = −yaw.
        panorama = lighting.probe_in_camera(torch.from_numpy(np.ascontiguousarray(probe)), h, w,
                                            rotation=-probe_yaw(self.spec, light, frame),
                                            cam_to_world=torch.from_numpy(camera_to_world(self.spec, frame)))
        return panorama.numpy()

    def scene_dict(self, frame: int, light: int) -> dict:
        """The Mitsuba scene description of one frame under probe `light`."""
        import mitsuba as mi

        T = mi.ScalarTransform4f
        spec = self.spec
        origin = camera_position(spec, frame)
        scene: dict = {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": 3},
            "sensor": {
                "type": "perspective", "fov": spec.camera.fov, "fov_axis": "x",
                "to_world": T().look_at(origin=origin.tolist(), target=list(spec.camera.target), up=[0, 1, 0]),
                "film": {"type": "hdrfilm", "width": self.size, "height": self.size, "pixel_format": "rgb",
                         # A box filter keeps the depth-derived mask from bleeding into neighbours.
                         "rfilter": {"type": "box"}},
                "sampler": {"type": "multijitter"},  # +3.5 dB over independent at equal cost
            },
            "env": {"type": "envmap", "bitmap": self._bitmaps[light],
                    "to_world": T().rotate([0, 1, 0], probe_yaw(spec, light, frame))},
            "ground": {"type": "rectangle",
                       "to_world": T().rotate([1, 0, 0], -90).scale([GROUND_SIZE / 2] * 3),
                       "bsdf": self._bsdf(spec.ground, 0, repeat_scale=GROUND_SIZE / 2)},
        }
        for i, obj in enumerate(spec.objects):
            x, z, yaw = object_pose(spec, obj, frame)
            placed = T().translate([x, 0, z]).rotate([0, 1, 0], yaw)
            bsdf = self._bsdf(obj.material, i + 1)
            if obj.shape == "sphere":
                r = obj.size[0]
                shape = {"type": "sphere", "to_world": placed.translate([0, r, 0]).scale(r)}
            elif obj.shape == "cube":
                shape = {"type": "cube", "to_world": placed.translate([0, obj.size[1], 0]).scale(list(obj.size))}
            else:
                shape = {"type": "ply", "filename": self._mesh_files[i], "to_world": placed.scale(list(obj.size))}
            scene[f"object{i}"] = {**shape, "bsdf": bsdf}
        return scene

    def _bsdf(self, mat: MaterialSpec, texture_index: int, repeat_scale: float = 1.0) -> dict:
        import mitsuba as mi

        if mat.texture is not None:
            k = mat.texture_repeat * repeat_scale
            base: dict = {"type": "bitmap", "bitmap": self._textures[texture_index], "filter_type": "bilinear",
                          "wrap_mode": "repeat", "to_uv": mi.ScalarTransform4f().scale([k, k, 1])}
        else:
            base = {"type": "rgb", "value": srgb_to_linear(np.asarray(mat.base_color)).tolist()}
        bsdf = {"type": "principled", "base_color": base, "roughness": mat.roughness,
                "metallic": mat.metallic, "specular": mat.specular, "spec_trans": mat.transmission}
        # Open meshes (the airplane's wings) show their back faces; glass needs its sidedness.
        return bsdf if mat.transmission > 0 else {"type": "twosided", "bsdf": bsdf}
