"""HDR light probes: loading, lat-long geometry, rotation, camera re-gridding, encodings, balls.

Conventions and the released code's behaviour they match are documented in
`relight_core.lighting.panorama`; file I/O and the per-pixel encodings live in `probe`; the
mirror/diffuse ball renders used by the previews live in `balls`.
"""

from relight_core.lighting.balls import diffuse_ball, mirror_ball, mirror_ball_to_latlong
from relight_core.lighting.panorama import (
    DEFAULT_ROTATION,
    direction_to_uv,
    frame_rotations,
    latlong_directions,
    panorama_directions,
    probe_frames,
    probe_in_camera,
    roll_probe,
    rotate_probe,
    rotation_sweep,
    sample_probe,
    texel_directions,
    uv_to_direction,
    yaw_matrix,
)
from relight_core.lighting.probe import (
    HDR_MAX,
    LOG_SCALE,
    REINHARD_WHITE,
    clean_hdr,
    encode_lighting,
    env_ldr,
    env_log,
    load_probe,
    reinhard,
    rgb_to_srgb,
    tonemap_display,
)

__all__ = [
    "DEFAULT_ROTATION",
    "HDR_MAX",
    "LOG_SCALE",
    "REINHARD_WHITE",
    "clean_hdr",
    "diffuse_ball",
    "direction_to_uv",
    "frame_rotations",
    "encode_lighting",
    "env_ldr",
    "env_log",
    "latlong_directions",
    "load_probe",
    "mirror_ball",
    "mirror_ball_to_latlong",
    "panorama_directions",
    "probe_frames",
    "probe_in_camera",
    "reinhard",
    "rgb_to_srgb",
    "roll_probe",
    "rotate_probe",
    "rotation_sweep",
    "sample_probe",
    "texel_directions",
    "tonemap_display",
    "uv_to_direction",
    "yaw_matrix",
]
