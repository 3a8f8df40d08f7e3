"""Per-pixel renders of a probe on a unit sphere (mirror and diffuse), and chrome ball → lat-long.

Camera: orthographic, looking down −Z at a unit sphere, as the released `get_ideal_ball` /
`process_ball_envmap` (normal x = linspace(−1, 1) left→right, y = linspace(1, −1) top→bottom,
mirror direction `2(n·v)n − v` with v = +Z towards the viewer). A ball pixel with camera-frame
direction r shows `probe(R_y(rotation)·c2w·r)`, the same look-up `probe_in_camera` uses, so a
preview at a given rotation shows the light the model is given at that rotation.
"""

import math

import torch
import torch.nn.functional as F

from relight_core.lighting.panorama import (
    DEFAULT_ROTATION,
    _camera_rotation,
    sample_probe,
    texel_directions,
    yaw_matrix,
)

_TO_VIEWER = torch.tensor([0.0, 0.0, 1.0])
_IRRADIANCE_GRID = (32, 64)  # probe resolution the diffuse integral runs at (≈ 5.6° texels)


def ball_normals(size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Sphere normals [size, size, 3] (zero outside) and the disc mask [size, size] bool."""
    y, x = torch.meshgrid(torch.linspace(1, -1, size), torch.linspace(-1, 1, size), indexing="ij")
    z2 = 1 - x**2 - y**2
    mask = z2 >= 0
    normals = torch.stack((x, y, z2.clamp(min=0).sqrt()), dim=-1) * mask[..., None]
    return normals, mask


def _world(directions: torch.Tensor, rotation: float, cam_to_world) -> torch.Tensor:
    return directions @ _camera_rotation(cam_to_world).T @ yaw_matrix(rotation).T


def mirror_ball(
    probe: torch.Tensor, size: int, rotation: float = DEFAULT_ROTATION, cam_to_world=None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Chrome sphere render: (linear image [size, size, 3], mask [size, size] bool)."""
    normals, mask = ball_normals(size)
    reflected = 2 * (normals @ _TO_VIEWER)[..., None] * normals - _TO_VIEWER  # [size, size, 3]
    image = sample_probe(probe, _world(reflected, rotation, cam_to_world)) * mask[..., None]
    return image, mask


def _irradiance_map(probe: torch.Tensor) -> torch.Tensor:
    """Lambertian radiance (1/π)∫L(ω)max(0, n·ω)dω for normals on a coarse lat-long grid [h, w, 3]."""
    h, w = _IRRADIANCE_GRID
    # Area-average the probe down so each texel carries its whole patch's energy (a sun survives).
    small = F.adaptive_avg_pool2d(probe.float().permute(2, 0, 1)[None], (h, w))[0].permute(1, 2, 0)
    dirs = texel_directions(h, w).reshape(-1, 3)  # [h·w, 3]
    theta = (torch.arange(h) + 0.5) * math.pi / h
    solid_angle = (torch.sin(theta) * (math.pi / h) * (2 * math.pi / w)).repeat_interleave(w)  # [h·w]
    weighted = small.reshape(-1, 3) * solid_angle[:, None] / math.pi  # [h·w, 3]
    cosine = (dirs @ dirs.T).clamp(min=0)  # [h·w (normals), h·w (light directions)]
    return (cosine @ weighted).reshape(h, w, 3)


def diffuse_ball(
    probe: torch.Tensor, size: int, rotation: float = DEFAULT_ROTATION, cam_to_world=None
) -> tuple[torch.Tensor, torch.Tensor]:
    """White Lambertian sphere: radiance (1/π)∫L(ω)max(0, n·ω)dω per pixel, plus the disc mask."""
    normals, mask = ball_normals(size)
    # Irradiance is smooth, so a bilinear look-up in a coarse irradiance map is accurate and fast.
    image = sample_probe(_irradiance_map(probe), _world(normals, rotation, cam_to_world)) * mask[..., None]
    return image, mask


def mirror_ball_to_latlong(
    ball: torch.Tensor, H: int, W: int, rotation: float = DEFAULT_ROTATION, cam_to_world=None
) -> torch.Tensor:
    """Invert `mirror_ball`: a chrome-ball image [S, S, 3] -> probe [H, W, 3] (the back pole is unseen)."""
    world = texel_directions(H, W)  # [H, W, 3]
    # World → camera frame: the transpose of the rotation `mirror_ball` applies.
    camera = world @ yaw_matrix(rotation) @ _camera_rotation(cam_to_world)
    normals = F.normalize(camera + _TO_VIEWER, dim=-1)  # half vector between view and light
    grid = torch.stack((normals[..., 0], -normals[..., 1]), dim=-1)[None]  # [1, H, W, 2]
    image = torch.as_tensor(ball, dtype=torch.float32).permute(2, 0, 1)[None]
    # The ball grid spans [−1, 1] with pixel centres on the end points: align_corners=True.
    out = F.grid_sample(image, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out[0].permute(1, 2, 0)
