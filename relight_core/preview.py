"""Off-screen pyvista previews of a light probe: a mirror ball, a diffuse ball and the panorama.

Every colour comes from the one ball renderer in `lighting` (`mirror_radiance`, `diffuse_radiance`,
`camera_radiance`): the look-up `lighting.probe_in_camera` makes to build the panorama the model
is given, so the preview and the model share one rotation convention (a test pins the two
together). pyvista only rasterises the spheres, coloured per vertex, with antialiased rims. The
balls are seen by an orthographic camera looking down −Z (the lat-long convention's forward), so
every pixel of a ball has the same view direction and its colour follows from its surface normal alone.
"""

from __future__ import annotations

import functools
import math
import os
import queue
import threading
from dataclasses import dataclass

# EGL on Mesa renders without an X server; set before VTK picks a window class.
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

import numpy as np
import torch

from relight_core import lighting

FORWARD = (0.0, 0.0, -1.0)  # the camera's forward direction, marked on the panorama


@dataclass(frozen=True)
class PreviewConfig:
    """Sizes of the preview image and the tessellation behind it."""

    ball_size: int = 256          # pixels per ball; the preview is 2·ball_size wide
    mirror_resolution: int = 160  # sphere tessellation of the mirror ball (reflections are sharp)
    diffuse_resolution: int = 64  # the diffuse ball is smooth, so a coarse mesh suffices
    irradiance_height: int = lighting.balls.IRRADIANCE_HEIGHT  # rows of the diffuse ball's irradiance map
    albedo: float = 0.8           # reflectance of the diffuse ball
    margin: float = 1.04          # half-height of the view in ball radii (a thin border)


# ---------------------------------------------------------------------------------------------
# Shading (pure torch; what the pyvista meshes are coloured with)
# ---------------------------------------------------------------------------------------------

@functools.lru_cache(maxsize=8)
def _texel_directions(height: int) -> torch.Tensor:
    return lighting.texel_directions(height, 2 * height).reshape(-1, 3)                # [h·2h, 3]


def camera_panorama(probe: torch.Tensor, rotation: float, height: int,
                    camera: torch.Tensor | None = None) -> torch.Tensor:
    """The camera-frame light in the standard lat-long layout (centre column = forward), [h,2h,3]."""
    return lighting.camera_radiance(probe, _texel_directions(height), rotation, camera).reshape(height, 2 * height, 3)


def to_display(linear: torch.Tensor) -> np.ndarray:
    """Linear colours [...,3] → uint8 with the same tonemap as the panorama preview."""
    flat = linear.reshape(-1, 1, 3)
    return np.asarray(lighting.tonemap_display(flat)).reshape(*linear.shape[:-1], 3)


# ---------------------------------------------------------------------------------------------
# Rendering
# ---------------------------------------------------------------------------------------------

def _sphere(resolution: int):
    import pyvista as pv

    # The poles sit left and right (±X), away from the centre and rim a viewer looks at.
    return pv.Sphere(radius=1.0, theta_resolution=resolution, phi_resolution=resolution,
                     direction=(1.0, 0.0, 0.0))


def _unit_normals(mesh) -> torch.Tensor:
    normals = torch.as_tensor(np.asarray(mesh.points), dtype=torch.float32)
    return normals / normals.norm(dim=1, keepdim=True)


class _BallRenderer:
    """One persistent off-screen plotter with a mirror and a diffuse sphere, on its own thread.

    VTK's OpenGL context belongs to the thread that created it (another thread's render fails),
    and building a plotter costs far more than re-colouring one, so the plotter lives on a
    dedicated thread and callers hand it per-vertex colours.
    """

    def __init__(self, config: PreviewConfig):
        self.config = config
        self.mirror = _sphere(config.mirror_resolution)
        self.diffuse = _sphere(config.diffuse_resolution)
        self.mirror_normals = _unit_normals(self.mirror)
        self.diffuse_normals = _unit_normals(self.diffuse)
        self._jobs: queue.Queue = queue.Queue()
        threading.Thread(target=self._serve, name="ball-renderer", daemon=True).start()

    def render(self, mirror_rgb: np.ndarray, diffuse_rgb: np.ndarray) -> np.ndarray:
        """uint8 [S, 2S, 3] image of the two balls coloured per vertex (uint8 [N,3] each)."""
        done: queue.Queue = queue.Queue(maxsize=1)
        self._jobs.put((mirror_rgb, diffuse_rgb, done))
        outcome = done.get()
        if isinstance(outcome, BaseException):
            raise outcome
        return outcome

    def _serve(self) -> None:
        import pyvista as pv

        size = self.config.ball_size
        plotter = pv.Plotter(off_screen=True, shape=(1, 2), window_size=(2 * size, size), border=False)
        # Supersampling smooths the balls' rims (offscreen EGL has no multisampling, and pyvista
        # replaces FXAA by SSAA there anyway).
        plotter.enable_anti_aliasing("ssaa")
        self.mirror["rgb"] = np.zeros((self.mirror.n_points, 3), np.uint8)
        self.diffuse["rgb"] = np.zeros((self.diffuse.n_points, 3), np.uint8)
        for column, mesh in enumerate((self.mirror, self.diffuse)):
            plotter.subplot(0, column)
            plotter.set_background((0.12, 0.12, 0.13))
            # Unlit: the colours already are the shading, so VTK must not add its own.
            plotter.add_mesh(mesh, scalars="rgb", rgb=True, lighting=False, show_scalar_bar=False)
            plotter.camera_position = [(0.0, 0.0, 10.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0)]
            plotter.enable_parallel_projection()
            plotter.camera.parallel_scale = self.config.margin
        while True:
            mirror_rgb, diffuse_rgb, done = self._jobs.get()
            try:
                self.mirror.point_data["rgb"] = mirror_rgb
                self.diffuse.point_data["rgb"] = diffuse_rgb
                plotter.render()
                image = plotter.screenshot(return_img=True)
                done.put(np.ascontiguousarray(image[:, :, :3]))
            except Exception as exc:  # handed to the waiting caller
                done.put(exc)


_RENDERERS: dict[PreviewConfig, _BallRenderer] = {}
_RENDERERS_LOCK = threading.Lock()


def _renderer(config: PreviewConfig) -> _BallRenderer:
    with _RENDERERS_LOCK:
        if config not in _RENDERERS:
            _RENDERERS[config] = _BallRenderer(config)
        return _RENDERERS[config]


def render_balls(probe: torch.Tensor, rotation: float, config: PreviewConfig = PreviewConfig(),
                 camera: torch.Tensor | None = None) -> np.ndarray:
    """Mirror ball (left) and diffuse ball (right) lit by the rotated probe, uint8 [S,2S,3]."""
    renderer = _renderer(config)
    mirror_rgb = to_display(lighting.mirror_radiance(probe, renderer.mirror_normals, rotation, camera))
    diffuse_rgb = to_display(config.albedo * lighting.diffuse_radiance(probe, renderer.diffuse_normals, rotation,
                                                                       camera, config.irradiance_height))
    return renderer.render(mirror_rgb, diffuse_rgb)


def panorama_image(panorama: torch.Tensor) -> np.ndarray:
    """The tonemapped camera-frame panorama, uint8 [h,w,3], with the camera's forward marked."""
    image = np.array(lighting.tonemap_display(panorama), dtype=np.uint8, copy=True)
    height, width = image.shape[:2]
    uv = np.asarray(lighting.direction_to_uv(torch.tensor([FORWARD])), dtype=np.float64)[0]
    col, row = int(uv[0] * width), int(uv[1] * height)
    arm, thick = max(4, height // 16), max(1, height // 128)
    # A two-tone cross reads on bright and dark skies alike.
    for colour, grow in (((0, 0, 0), thick + 1), ((255, 64, 32), thick)):
        r0, r1 = max(row - arm, 0), min(row + arm + 1, height)
        c0, c1 = max(col - arm, 0), min(col + arm + 1, width)
        image[r0:r1, max(col - grow, 0):col + grow + 1] = colour
        image[max(row - grow, 0):row + grow + 1, c0:c1] = colour
    return image


def probe_thumbnail(probe: torch.Tensor, height: int) -> np.ndarray:
    """The probe file's own panorama (no rotation), area-averaged to [height, 2·height], uint8."""
    probe = torch.as_tensor(probe, dtype=torch.float32)
    small = torch.nn.functional.adaptive_avg_pool2d(probe.permute(2, 0, 1)[None], (height, 2 * height))
    return np.asarray(lighting.tonemap_display(small[0].permute(1, 2, 0)), dtype=np.uint8)


def render_preview(probe: torch.Tensor, rotation: float = lighting.DEFAULT_ROTATION,
                   intensity: float = 1.0, config: PreviewConfig = PreviewConfig(),
                   temperature: float = lighting.NEUTRAL_KELVIN, pitch: float = 0.0,
                   roll: float = 0.0, tint: float = 0.0) -> np.ndarray:
    """The light preview: balls on top, panorama below, uint8 [S + S, 2S, 3].

    The probe gets its exposure, colour temperature and tint from `lighting.adjust_light`, and the camera
    its tilt from `lighting.camera_rotation(pitch, roll)`, as the pipeline's request does, so the
    preview shows the light the model is given (a tilted camera moves the horizon and the balls).
    """
    probe = lighting.adjust_light(probe, intensity, temperature, tint)
    camera = lighting.camera_rotation(pitch, roll)
    balls = render_balls(probe, rotation, config, camera)
    strip = panorama_image(camera_panorama(probe, rotation, config.ball_size, camera))
    return np.concatenate([balls, strip], axis=0)


def ball_pixel_direction(row: float, col: float, size: int, margin: float = PreviewConfig.margin) -> np.ndarray:
    """The mirror direction seen at pixel (row, col) of a mirror ball rendered at `size` (for tests)."""
    x = (col + 0.5 - size / 2) / (size / 2) * margin
    y = -(row + 0.5 - size / 2) / (size / 2) * margin
    z = math.sqrt(max(0.0, 1.0 - x * x - y * y))
    normal = torch.tensor([[x, y, z]], dtype=torch.float32)
    normal = normal / normal.norm()
    return lighting.reflect_view(normal)[0].numpy()
