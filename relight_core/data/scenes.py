"""Random scene descriptions, deterministic from (seed, split, index): geometry, materials, probes, motion.

A `SceneSpec` is plain data (frozen dataclasses, JSON-serialisable through `asdict`); the renderer
turns it into Mitsuba scenes frame by frame. World frame: Y up, ground plane y = 0, scene centred
on the origin.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass

import numpy as np

from relight_core.data.meshes import MESHES, build_mesh
from relight_core.data.probes import DARK_SOURCES, ProbeChoice, probe_names
from relight_core.data.textures import TEXTURE_KINDS, TextureSpec

SPLITS = ("train", "test")
MOTIONS = ("orbit", "oscillate", "light", "objects")
PLACEMENT_RADIUS = 1.3  # objects stand inside this disc on the ground
GROUND_SIZE = 16.0      # side of the square ground plane


@dataclass(frozen=True)
class MaterialSpec:
    """Principled BSDF parameters; base colour sRGB, replaced by `texture` when given."""

    base_color: tuple[float, float, float]
    texture: TextureSpec | None
    texture_repeat: float   # texture tiles per unit of the shape's uv range
    roughness: float
    metallic: float         # 1 = rough conductor tinted by the base colour
    specular: float
    transmission: float     # 1 = glass (rough dielectric tinted by the base colour)


@dataclass(frozen=True)
class ObjectSpec:
    """One object on the ground: a catalogue mesh or a primitive, with its motion."""

    shape: str                          # catalogue mesh name, or "cube" / "sphere" / "cylinder"
    shape_seed: int                     # shape parameters of procedural meshes
    size: tuple[float, float, float]    # x/y/z scale (cube: half extents; sphere: radius ×3)
    position: tuple[float, float]       # x, z on the ground at frame 0
    yaw: float                          # degrees at frame 0
    spin: float                         # degrees of yaw added over the clip
    shift: tuple[float, float]          # x, z translation over the clip
    footprint: float                    # radius of the ground footprint (after scaling)
    material: MaterialSpec


@dataclass(frozen=True)
class CameraSpec:
    """A camera looking at `target` from `distance`, with its motion over the clip."""

    target: tuple[float, float, float]
    distance: float
    elevation: float    # degrees above the ground
    azimuth: float      # degrees, 0 = camera on +Z looking down −Z
    fov: float          # horizontal field of view, degrees
    orbit: float        # degrees of azimuth travelled over the clip
    oscillation: float  # amplitude (degrees) of a back-and-forth sway in azimuth and elevation
    cycles: float       # sway periods per clip


@dataclass(frozen=True)
class SceneSpec:
    """Everything needed to render one scene under its two probes."""

    split: str
    seed: int
    index: int
    frames: int
    motion: tuple[str, ...]
    ground: MaterialSpec
    objects: tuple[ObjectSpec, ...]
    probes: tuple[ProbeChoice, ProbeChoice]
    light_sweep: float  # degrees of probe yaw added over the clip (both probes alike)
    camera: CameraSpec


def sample_scene(seed: int, split: str, index: int, frames: int, library: str = "classic") -> SceneSpec:
    """A random scene, identical for identical (seed, split, index, frames, library); `library` is the probe
    library (probes.PROBE_LIBRARIES: "extended" draws the train split's probes from more HDRIs, nothing else
    changes)."""
    rng = np.random.default_rng([seed, SPLITS.index(split), index])
    textures = TEXTURE_KINDS[split]
    motion: tuple[str, ...] = ()
    if frames > 1:
        motion = tuple(sorted(set(rng.choice(MOTIONS, size=1 + int(rng.random() < 0.3)).tolist())))

    objects: list[ObjectSpec] = []
    n_meshes, n_primitives = int(rng.integers(0, 4)), int(rng.integers(0, 4))
    if n_meshes + n_primitives == 0:
        n_primitives = 1
    shapes = [str(rng.choice(MESHES[split])) for _ in range(n_meshes)]
    shapes += [str(rng.choice(("cube", "sphere", "cylinder"))) for _ in range(n_primitives)]
    for shape in shapes:
        obj = _sample_object(rng, shape, textures, moving="objects" in motion)
        placed = _place(rng, obj, objects)
        if placed is not None:
            objects.append(placed)

    ground = _sample_material(rng, textures, allow_special=False, textured_p=0.75)
    names = probe_names(split, library)
    picked = rng.choice(len(names), size=2, replace=False)
    probes = tuple(_sample_probe(rng, names[int(i)]) for i in picked)

    camera = CameraSpec(
        target=(0.0, float(rng.uniform(0.25, 0.5)), 0.0),
        distance=float(rng.uniform(2.6, 3.8)),
        elevation=float(rng.uniform(8, 35)),
        azimuth=float(rng.uniform(-180, 180)),
        fov=float(rng.uniform(38, 55)),
        orbit=float(rng.choice([-1, 1]) * rng.uniform(30, 120)) if "orbit" in motion else 0.0,
        oscillation=float(rng.uniform(5, 15)) if "oscillate" in motion else 0.0,
        cycles=float(rng.uniform(0.5, 1.5)),
    )
    light_sweep = float(rng.choice([-1, 1]) * rng.uniform(60, 360)) if "light" in motion else 0.0
    return SceneSpec(split, seed, index, frames, motion, ground, tuple(objects), probes,  # type: ignore[arg-type]
                     light_sweep, camera)


# ---------------------------------------------------------------- poses over time

def clip_time(spec: SceneSpec, frame: int) -> float:
    """Normalised time of a frame in [0, 1] (0 for a one-frame clip)."""
    return frame / (spec.frames - 1) if spec.frames > 1 else 0.0


def camera_position(spec: SceneSpec, frame: int) -> np.ndarray:
    """World position of the camera at a frame."""
    cam, s = spec.camera, clip_time(spec, frame)
    sway = math.sin(2 * math.pi * cam.cycles * s)
    azimuth = math.radians(cam.azimuth + cam.orbit * s + cam.oscillation * sway)
    elevation = math.radians(cam.elevation + 0.4 * cam.oscillation * sway)
    offset = cam.distance * np.array([math.cos(elevation) * math.sin(azimuth), math.sin(elevation),
                                      math.cos(elevation) * math.cos(azimuth)])
    return np.asarray(cam.target) + offset


def camera_to_world(spec: SceneSpec, frame: int) -> np.ndarray:
    """3×3 rotation taking camera-frame directions (x right, y up, looking down −Z) to world."""
    origin, target = camera_position(spec, frame), np.asarray(spec.camera.target)
    forward = (target - origin) / np.linalg.norm(target - origin)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return np.stack([right, up, -forward], axis=1).astype(np.float32)


def object_pose(spec: SceneSpec, obj: ObjectSpec, frame: int) -> tuple[float, float, float]:
    """(x, z, yaw in degrees) of an object at a frame."""
    s = clip_time(spec, frame)
    return obj.position[0] + obj.shift[0] * s, obj.position[1] + obj.shift[1] * s, obj.yaw + obj.spin * s


def probe_yaw(spec: SceneSpec, light: int, frame: int) -> float:
    """World yaw (degrees about +Y) of probe `light` at a frame."""
    return spec.probes[light].rotation + spec.light_sweep * clip_time(spec, frame)


# ---------------------------------------------------------------- sampling helpers

def _random_srgb(rng: np.random.Generator) -> tuple[float, float, float]:
    h, s, v = rng.uniform(0, 1), rng.uniform(0, 0.9), rng.uniform(0.25, 0.95)
    return tuple(round(c, 4) for c in colorsys.hsv_to_rgb(h, s, v))  # type: ignore[return-value]


def _sample_material(rng: np.random.Generator, textures: tuple[str, ...], allow_special: bool,
                     textured_p: float) -> MaterialSpec:
    kind = rng.choice(["plastic", "metal", "glass"], p=[0.7, 0.15, 0.15]) if allow_special else "plastic"
    texture = None
    if rng.random() < textured_p:
        texture = TextureSpec(kind=str(rng.choice(textures)), color_a=_random_srgb(rng),
                              color_b=_random_srgb(rng), frequency=float(rng.integers(2, 9)),
                              angle=float(rng.uniform(0, math.pi)), seed=int(rng.integers(2**31)))
    return MaterialSpec(
        base_color=_random_srgb(rng),
        texture=texture,
        texture_repeat=float(rng.choice([1, 2, 3])),
        roughness=float(rng.uniform(0.05, 0.5) if kind != "plastic" else rng.uniform(0.1, 0.95)),
        metallic=1.0 if kind == "metal" else 0.0,
        specular=float(rng.uniform(0.2, 0.8)),
        transmission=1.0 if kind == "glass" else 0.0,
    )


def _sample_object(rng: np.random.Generator, shape: str, textures: tuple[str, ...],
                   moving: bool) -> ObjectSpec:
    shape_seed = int(rng.integers(2**31))
    if shape == "cube":
        size = tuple(float(v) for v in rng.uniform(0.2, 0.5, size=3))
        footprint = math.hypot(size[0], size[2])
    elif shape == "sphere":
        r = float(rng.uniform(0.2, 0.5))
        size, footprint = (r, r, r), r
    else:
        k = float(rng.uniform(0.35, 0.7))
        size = (k, k, k)
        footprint = build_mesh(shape, shape_seed).footprint * k
    spin = float(rng.choice([-1, 1]) * rng.uniform(30, 180)) if moving else 0.0
    shift = tuple(float(v) for v in rng.uniform(-0.5, 0.5, size=2)) if moving and rng.random() < 0.5 else (0.0, 0.0)
    return ObjectSpec(shape, shape_seed, size, (0.0, 0.0), float(rng.uniform(0, 360)), spin, shift,  # type: ignore[arg-type]
                      footprint, _sample_material(rng, textures, allow_special=True, textured_p=0.5))


def _place(rng: np.random.Generator, obj: ObjectSpec, placed: list[ObjectSpec]) -> ObjectSpec | None:
    """Drop the object where its swept footprint clears all others, or None after 100 tries."""
    sweep = 0.5 * math.hypot(*obj.shift)
    for _ in range(100):
        r = PLACEMENT_RADIUS * math.sqrt(rng.random())
        a = rng.uniform(0, 2 * math.pi)
        mid = np.array([r * math.cos(a), r * math.sin(a)])
        if all(np.linalg.norm(mid - _midpoint(o)) > obj.footprint + sweep + o.footprint
               + 0.5 * math.hypot(*o.shift) + 0.05 for o in placed):
            start = mid - 0.5 * np.asarray(obj.shift)
            return ObjectSpec(**{**obj.__dict__, "position": (float(start[0]), float(start[1]))})
    return None


def _midpoint(obj: ObjectSpec) -> np.ndarray:
    return np.asarray(obj.position) + 0.5 * np.asarray(obj.shift)


def _sample_probe(rng: np.random.Generator, source: str) -> ProbeChoice:
    dark = source in DARK_SOURCES
    low, high = (0.15, 0.4) if dark else (0.4, 1.0)
    return ProbeChoice(source=source, seed=int(rng.integers(2**31)), rotation=float(rng.uniform(0, 360)),
                       exposure=float(math.exp(rng.uniform(math.log(low), math.log(high)))))
