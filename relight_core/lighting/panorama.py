"""Lat-long geometry: directions, sampling, yaw rotation and re-gridding into the camera frame.

Facts read from the released UniRelight code (nv-tlabs/UniRelight,
`cosmos_predict1/diffusion/training/datasets/diffusion_renderer_dataloader/`), which the
released weights were trained against:

* `rendering_utils.latlong_to_cubemap` samples the file at
  `u = atan2(d.x, -d.z)/(2π) + 0.5`, `v = acos(d.y)/π` (bilinear, texel centres at
  `(j + 0.5)/w`), i.e. Y-up, row 0 straight up, the file's centre column looking down −Z.
* `rendering_utils.latlong_vec(H, W)` builds the panorama grid with
  `θ = π·linspace(1/H, 1 − 1/H, H)` (not the texel centres `(i + 0.5)/H`: a quirk kept here),
  `φ = π·linspace(−1 + 1/W, 1 − 1/W, W)` and `d = (sinθ sinφ, cosθ, −sinθ cosφ)`.
* `utils_env_proj.load_and_preprocess_hdr` multiplies by the strength, maps NaN→0, +Inf→65504,
  −Inf→0, clamps to [0, 65504], then `torch.roll`s the file by `int(w·rot/360)` columns
  (content moves towards +u); `env_rot` defaults to 180.
* `utils_env_proj.process_projected_envmap` looks up `-(R_y(a)·c2w·latlong_vec)` and flips the
  result along H and W. Because `latlong_vec` is symmetric, that equals looking up
  `R_y(a)·c2w·e` with `e = −latlong_vec.flip(0).flip(1) = (x, y, −z)` — exactly the
  `envmap_vec` that `single_gpu_relight.py` hands to the model as `env_nrm` (our `env_dir`).
  So the panorama's pixel (i, j) holds the light arriving from camera-frame direction
  `e[i, j]`; its centre column is camera +Z, its edge columns camera −Z.
* `rotate_y(a) = [[c, 0, s], [0, 1, 0], [−s, 0, c]]`; a roll by `rot` degrees equals a lookup
  at `R_y(rot)·d`. "Rotate light" uses `np.linspace(0, 2π, T)`, endpoint included.
* The released code goes through a 512² cubemap and nvdiffrast; this module samples the
  lat-long directly (bilinear, wrapping across the seam, clamped at the poles) and applies the
  rotation exactly instead of the truncated integer roll, so values differ at the sub-texel level.
"""

import math

import numpy as np
import torch
import torch.nn.functional as F

from relight_core.errors import InputError

DEFAULT_ROTATION = 180.0  # released `env_rot` default, degrees of yaw
MAX_ROTATION_DEG = 3600.0  # ten turns; a larger yaw or sweep end is a typo (same as relight_core.arguments)


def _as_tensor(x) -> torch.Tensor:
    return torch.as_tensor(x, dtype=torch.float32)


def _spherical(theta: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """Direction for polar angle θ from +Y and azimuth φ from −Z towards +X."""
    sin_t = torch.sin(theta)
    return torch.stack((sin_t * torch.sin(phi), torch.cos(theta), -sin_t * torch.cos(phi)), dim=-1)


def uv_to_direction(uv) -> torch.Tensor:
    """Unit directions [..., 3] of lat-long coordinates uv [..., 2] in [0, 1]."""
    uv = _as_tensor(uv).double()
    d = _spherical(math.pi * uv[..., 1], 2 * math.pi * (uv[..., 0] - 0.5))
    return d.float()


def direction_to_uv(d) -> torch.Tensor:
    """Lat-long coordinates [..., 2] of directions d [..., 3]: u = 0.5 + atan2(x, −z)/2π, v = acos(y)/π."""
    d = F.normalize(_as_tensor(d).double(), dim=-1)
    u = 0.5 + torch.atan2(d[..., 0], -d[..., 2]) / (2 * math.pi)
    v = torch.acos(d[..., 1].clamp(-1.0, 1.0)) / math.pi
    return torch.stack((u, v), dim=-1).float()


def texel_directions(h: int, w: int) -> torch.Tensor:
    """Directions [h, w, 3] of a probe file's texel centres ((j + 0.5)/w, (i + 0.5)/h)."""
    v = (torch.arange(h, dtype=torch.float64) + 0.5) / h
    u = (torch.arange(w, dtype=torch.float64) + 0.5) / w
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return _spherical(math.pi * vv, 2 * math.pi * (uu - 0.5)).float()


def latlong_directions(H: int, W: int) -> torch.Tensor:
    """Directions [H, W, 3] of the released `latlong_vec` grid (rows at linspace(1/H, 1 − 1/H))."""
    gy = torch.linspace(1.0 / H, 1.0 - 1.0 / H, H, dtype=torch.float64)
    gx = torch.linspace(-1.0 + 1.0 / W, 1.0 - 1.0 / W, W, dtype=torch.float64)
    theta, phi = torch.meshgrid(math.pi * gy, math.pi * gx, indexing="ij")
    return _spherical(theta, phi).float()


def panorama_directions(H: int, W: int) -> torch.Tensor:
    """Camera-frame direction [H, W, 3] of each pixel of the model's panorama (released `envmap_vec`)."""
    d = latlong_directions(H, W)
    return d * torch.tensor([1.0, 1.0, -1.0])  # = −d.flip(0).flip(1): the grid is symmetric


def yaw_matrix(degrees: float) -> torch.Tensor:
    """3×3 rotation about +Y by `degrees` (released `rotate_y`)."""
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=torch.float32)


def _sample_uv(probe: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear look-up of probe [h, w, 3] at uv [..., 2] -> [..., 3]; u wraps, v clamps at the poles."""
    probe = torch.as_tensor(probe, dtype=torch.float32)
    h, w, _ = probe.shape
    # Pad one column each side so bilinear taps across the u = 0/1 seam read the far edge.
    padded = torch.cat((probe[:, -1:], probe, probe[:, :1]), dim=1)  # [h, w+2, 3]
    x_pix = torch.remainder(uv[..., 0], 1.0) * w - 0.5 + 1.0  # texel index in the padded map
    y_pix = uv[..., 1] * h - 0.5
    grid = torch.stack(((2 * x_pix + 1) / (w + 2) - 1, (2 * y_pix + 1) / h - 1), dim=-1)
    grid = grid.float().reshape(1, 1, -1, 2)
    image = padded.permute(2, 0, 1).unsqueeze(0).contiguous()  # [1, 3, h, w+2]
    out = F.grid_sample(image, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out[0, :, 0].T.reshape(*uv.shape[:-1], 3)


def sample_probe(probe: torch.Tensor, directions) -> torch.Tensor:
    """Bilinear look-up of probe [h, w, 3] along directions [..., 3] -> [..., 3], wrapping in u."""
    return _sample_uv(probe, direction_to_uv(directions))


def rotate_probe(probe: torch.Tensor, degrees: float) -> torch.Tensor:
    """Exact yaw of a probe: out(d) = probe(R_y(degrees)·d); +90° moves −Z light to +X (u + 1/4)."""
    h, w, _ = probe.shape
    dirs = texel_directions(h, w) @ yaw_matrix(degrees).T  # [h, w, 3]
    return sample_probe(probe, dirs)


def roll_probe(probe: torch.Tensor, degrees: float) -> torch.Tensor:
    """The released integer roll: `torch.roll` by int(w·degrees/360) columns."""
    return torch.roll(probe, shifts=int(probe.shape[1] * degrees / 360), dims=1)


def rotation_sweep(num_frames: int, start: float = 0.0, end: float = 360.0) -> list[float]:
    """Per-frame yaw in degrees for "rotate light": linspace(start, end, T), endpoint included."""
    return [float(a) for a in np.linspace(start, end, num_frames)]


def frame_rotations(num_frames: int, rotation: float = DEFAULT_ROTATION, rotate_light: bool = False,
                    sweep: tuple[float, float] = (0.0, 360.0)) -> list[float]:
    """The yaw of each frame: `rotation`, plus the sweep angle of that frame when the light rotates.

    Angles must be finite and within ±MAX_ROTATION_DEG (ten turns); others raise InputError.
    """
    for name, value in (("light rotation", rotation), ("sweep start", sweep[0]), ("sweep end", sweep[1])):
        if not (math.isfinite(float(value)) and abs(float(value)) <= MAX_ROTATION_DEG):
            raise InputError(f"The {name} {value} is not a usable angle; use a finite number of degrees "
                             f"between -{MAX_ROTATION_DEG:g} and {MAX_ROTATION_DEG:g}.")
    angles = rotation_sweep(num_frames, *sweep) if rotate_light else [0.0] * num_frames
    return [float(rotation) + angle for angle in angles]


def _camera_rotation(cam_to_world) -> torch.Tensor:
    if cam_to_world is None:
        return torch.eye(3)
    return _as_tensor(cam_to_world)[..., :3, :3]


def _camera_uv(H: int, W: int, cam_to_world) -> torch.Tensor:
    """uv [H, W, 2] of the world directions c2w·e of the panorama pixels, before any yaw."""
    return direction_to_uv(panorama_directions(H, W) @ _camera_rotation(cam_to_world).T)


def _yawed(uv: torch.Tensor, degrees: float) -> torch.Tensor:
    # R_y(a) lowers the azimuth by a, so a yaw is an exact shift of u: no trigonometry per frame.
    return uv - torch.tensor([degrees / 360.0, 0.0])


def probe_in_camera(
    probe: torch.Tensor, H: int, W: int, rotation: float = DEFAULT_ROTATION, cam_to_world=None
) -> torch.Tensor:
    """The full panorama [H, W, 3] in the camera frame: pixel e holds probe(R_y(rotation)·c2w·e)."""
    return _sample_uv(probe, _yawed(_camera_uv(H, W, cam_to_world), rotation))


def camera_radiance(probe: torch.Tensor, directions, rotation: float = DEFAULT_ROTATION,
                    cam_to_world=None) -> torch.Tensor:
    """Radiance [..., 3] arriving from camera-frame directions [..., 3]: probe(R_y(rotation)·c2w·d),
    the look-up `probe_in_camera` makes, at any directions (the preview's balls and panorama)."""
    world = _as_tensor(directions) @ _camera_rotation(cam_to_world).T @ yaw_matrix(rotation).T
    return sample_probe(probe, world)


def probe_frames(
    probe: torch.Tensor,
    T: int,
    H: int,
    W: int,
    rotation: float = DEFAULT_ROTATION,
    rotate_light: bool = False,
    sweep: tuple[float, float] = (0.0, 360.0),
    cam_to_world=None,
) -> torch.Tensor:
    """Per-frame camera-frame panoramas [T, H, W, 3]; cam_to_world is [3, 3] or per frame [T, 3, 3]."""
    cams = _camera_rotation(cam_to_world)
    per_frame_camera = cams.dim() == 3
    if not rotate_light and not per_frame_camera:
        return probe_in_camera(probe, H, W, rotation, cams).expand(T, H, W, 3).contiguous()
    fixed_uv = None if per_frame_camera else _camera_uv(H, W, cams)
    frames = torch.empty(T, H, W, 3)
    for t, yaw in enumerate(frame_rotations(T, rotation, rotate_light, sweep)):
        uv = _camera_uv(H, W, cams[t]) if per_frame_camera else fixed_uv
        frames[t] = _sample_uv(probe, _yawed(uv, yaw))
    return frames


def downsample_panorama(panoramas: torch.Tensor, size: int) -> torch.Tensor:
    """[T, H, W, 3] → [T, size, size, 3] by area averaging (energy-preserving: a sun stays bright)."""
    x = _as_tensor(panoramas).float().permute(0, 3, 1, 2)                  # (T, 3, H, W)
    x = torch.nn.functional.interpolate(x, size=(size, size), mode="area")
    return x.permute(0, 2, 3, 1).contiguous()


def upsample_panorama(small: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """[T, s, s, 3] → [T, H, W, 3], bilinear with pixel centres aligned (align_corners=False)."""
    x = _as_tensor(small).float().permute(0, 3, 1, 2)
    x = torch.nn.functional.interpolate(x, size=(H, W), mode="bilinear", align_corners=False)
    return x.permute(0, 2, 3, 1).contiguous()


def lowpass_panorama(panoramas: torch.Tensor, size: int | None) -> torch.Tensor:
    """Camera-frame panoramas [T, H, W, 3] seen through a `size`² grid, back at H×W.

    A model trained with a lighting resolution (`ModelSpec.lighting_size`) sees its probes this way
    in training and at inference alike; None or a size ≥ H and W returns the input unchanged.
    """
    T, H, W, _ = panoramas.shape
    if size is None or (size >= H and size >= W):
        return panoramas
    return upsample_panorama(downsample_panorama(panoramas, size), H, W)


def _panorama_axis_matrix(src: int, dst: int, periodic: bool) -> torch.Tensor:
    """[dst, src] weights re-gridding one axis of the panorama grid (`latlong_directions`).

    Rows sit at θ = π·linspace(1/n, 1 − 1/n, n) (clamped at the poles), columns at
    φ = π·linspace(−1 + 1/n, 1 − 1/n, n) (periodic). Each output sample averages ⌈ratio⌉ bilinear
    taps spread over its own cell, a box prefilter when shrinking, plain bilinear when enlarging.
    """
    def grid(n: int) -> np.ndarray:
        return np.linspace(-1 + 1 / n, 1 - 1 / n, n) if periodic else np.linspace(1 / n, 1 - 1 / n, n)

    source, target = grid(src), grid(dst)
    source_step = 2 / src if periodic else (source[1] - source[0] if src > 1 else 1.0)
    cell = 2 / dst if periodic else (target[1] - target[0] if dst > 1 else 1.0)
    taps = max(1, math.ceil(cell / source_step - 1e-9))
    points = target[:, None] + ((np.arange(taps) + 0.5) / taps - 0.5) * cell          # [dst, taps]
    if periodic:
        index = (points - source[0]) / source_step
        low = np.floor(index)
        frac, low = index - low, low.astype(np.int64) % src
        high = (low + 1) % src
    else:
        index = np.interp(points, source, np.arange(src, dtype=np.float64))           # clamps at the poles
        low = np.minimum(np.floor(index).astype(np.int64), src - 1)
        frac, high = index - low, np.minimum(low + 1, src - 1)
    weights = np.zeros((dst, src))
    rows = np.repeat(np.arange(dst), taps)
    np.add.at(weights, (rows, low.ravel()), (1 - frac).ravel() / taps)
    np.add.at(weights, (rows, high.ravel()), frac.ravel() / taps)
    return torch.from_numpy(weights).float()


def resize_panorama(panoramas, H: int, W: int) -> torch.Tensor:
    """Camera-frame panoramas [..., h, w, 3] (the `probe_in_camera` grid) re-gridded to [..., H, W, 3].

    Each output pixel holds the light from its own camera-frame direction (`panorama_directions(H, W)`),
    so a panorama rendered at one frame size can condition a model run at another. The same size
    returns the input unchanged; shrinking box-filters so a small sun keeps its energy.
    """
    panoramas = _as_tensor(panoramas)
    h, w = panoramas.shape[-3:-1]
    if (h, w) == (H, W):
        return panoramas
    rows = _panorama_axis_matrix(h, H, periodic=False)
    cols = _panorama_axis_matrix(w, W, periodic=True)
    return torch.einsum("Ih,...hwc,Jw->...IJc", rows, panoramas, cols).contiguous()
