"""The one renderer of a probe on a unit sphere (mirror and diffuse), and chrome ball → lat-long.

Camera: orthographic, looking down −Z at a unit sphere, as the released `get_ideal_ball` /
`process_ball_envmap` (normal x = linspace(−1, 1) left→right, y = linspace(1, −1) top→bottom,
mirror direction `2(n·v)n − v` with v = +Z towards the viewer). A surface with camera-frame
direction r shows `probe(R_y(rotation)·c2w·r)` (`camera_radiance`), the same look-up
`probe_in_camera` uses, so a ball at a given rotation shows the light the model is given at that
rotation. `mirror_radiance` / `diffuse_radiance` shade any camera-frame normals (the studio
preview's pyvista spheres colour their vertices with them); `mirror_ball` / `diffuse_ball` are
the same shading per pixel.
"""

import functools
import math

import torch
import torch.nn.functional as F

from relight_core.lighting.panorama import (
    DEFAULT_ROTATION,
    _camera_rotation,
    camera_radiance,
    texel_directions,
    yaw_matrix,
)

TO_VIEWER = (0.0, 0.0, 1.0)  # unit vector from a ball towards the (orthographic) camera
IRRADIANCE_HEIGHT = 32       # rows of the lat-long grid the diffuse integral runs at (≈ 5.6° texels)


def ball_normals(size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Sphere normals [size, size, 3] (zero outside) and the disc mask [size, size] bool."""
    y, x = torch.meshgrid(torch.linspace(1, -1, size), torch.linspace(-1, 1, size), indexing="ij")
    z2 = 1 - x**2 - y**2
    mask = z2 >= 0
    normals = torch.stack((x, y, z2.clamp(min=0).sqrt()), dim=-1) * mask[..., None]
    return normals, mask


def reflect_view(normals: torch.Tensor) -> torch.Tensor:
    """Mirror directions [..., 3] for unit camera-frame normals [..., 3] seen along TO_VIEWER."""
    view = torch.tensor(TO_VIEWER, dtype=normals.dtype)
    return 2 * (normals @ view)[..., None] * normals - view


def mirror_radiance(probe: torch.Tensor, normals: torch.Tensor, rotation: float = DEFAULT_ROTATION,
                    cam_to_world=None) -> torch.Tensor:
    """Linear radiance [..., 3] a perfect mirror with these camera-frame normals shows."""
    return camera_radiance(probe, reflect_view(normals), rotation, cam_to_world)


@functools.lru_cache(maxsize=4)
def _irradiance_kernel(height: int) -> torch.Tensor:
    """[h·w (normals), h·w (light texels)]: max(0, n·ω)·dω/π on the lat-long grid of `height` rows."""
    h, w = height, 2 * height
    dirs = texel_directions(h, w).reshape(-1, 3)  # [h·w, 3]
    theta = (torch.arange(h) + 0.5) * math.pi / h
    solid_angle = (torch.sin(theta) * (math.pi / h) * (2 * math.pi / w)).repeat_interleave(w)  # [h·w]
    return (dirs @ dirs.T).clamp(min=0) * (solid_angle / math.pi)


def irradiance_map(probe: torch.Tensor, height: int = IRRADIANCE_HEIGHT) -> torch.Tensor:
    """Lambertian radiance (1/π)∫L(ω)max(0, n·ω)dω for normals n on a lat-long grid [height, 2·height, 3]."""
    h, w = height, 2 * height
    # Area-average the probe down so each texel carries its whole patch's energy (a sun survives).
    small = F.adaptive_avg_pool2d(probe.float().permute(2, 0, 1)[None], (h, w))[0].permute(1, 2, 0)
    return (_irradiance_kernel(height) @ small.reshape(-1, 3)).reshape(h, w, 3)


def diffuse_radiance(probe: torch.Tensor, normals: torch.Tensor, rotation: float = DEFAULT_ROTATION,
                     cam_to_world=None, height: int = IRRADIANCE_HEIGHT) -> torch.Tensor:
    """Linear radiance [..., 3] of a white Lambertian surface with these camera-frame normals."""
    # Irradiance is smooth, so a bilinear look-up in a coarse irradiance map is accurate and fast.
    return camera_radiance(irradiance_map(probe, height), normals, rotation, cam_to_world)


def mirror_ball(
    probe: torch.Tensor, size: int, rotation: float = DEFAULT_ROTATION, cam_to_world=None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Chrome sphere render: (linear image [size, size, 3], mask [size, size] bool)."""
    normals, mask = ball_normals(size)
    return mirror_radiance(probe, normals, rotation, cam_to_world) * mask[..., None], mask


def diffuse_ball(
    probe: torch.Tensor, size: int, rotation: float = DEFAULT_ROTATION, cam_to_world=None
) -> tuple[torch.Tensor, torch.Tensor]:
    """White Lambertian sphere: radiance (1/π)∫L(ω)max(0, n·ω)dω per pixel, plus the disc mask."""
    normals, mask = ball_normals(size)
    return diffuse_radiance(probe, normals, rotation, cam_to_world) * mask[..., None], mask


def mirror_ball_to_latlong(
    ball: torch.Tensor, H: int, W: int, rotation: float = DEFAULT_ROTATION, cam_to_world=None
) -> torch.Tensor:
    """Invert `mirror_ball`: a chrome-ball image [S, S, 3] -> probe [H, W, 3] (the back pole is unseen)."""
    world = texel_directions(H, W)  # [H, W, 3]
    # World → camera frame: the transpose of the rotation `mirror_ball` applies.
    camera = world @ yaw_matrix(rotation) @ _camera_rotation(cam_to_world)
    normals = F.normalize(camera + torch.tensor(TO_VIEWER), dim=-1)  # half vector between view and light
    grid = torch.stack((normals[..., 0], -normals[..., 1]), dim=-1)[None]  # [1, H, W, 2]
    image = torch.as_tensor(ball, dtype=torch.float32).permute(2, 0, 1)[None]
    # The ball grid spans [−1, 1] with pixel centres on the end points: align_corners=True.
    out = F.grid_sample(image, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out[0].permute(1, 2, 0)
