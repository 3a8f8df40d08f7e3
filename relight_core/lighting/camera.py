"""The camera's tilt: pitch and roll as the camera-to-world rotation the lighting look-ups take.

The model's lighting is in the camera frame, and `probe_in_camera(..., cam_to_world)` looks up
`probe(R_y(rotation)·c2w·e)` for each camera-frame direction e. A level camera is c2w = I; a photo
taken looking up, or with the camera turned about its lens axis, is

    c2w = R_x(pitch) · R_z(roll)

(roll first, about the camera's own view axis −Z; then pitch, about its right axis +X). Positive
pitch turns the camera's view (−Z) upwards (towards +Y), so the horizon of the camera-frame
panorama moves down; positive roll turns the camera's top (+Y) to its left (−X), counter-clockwise
as seen from behind it, so the horizon in the picture turns clockwise.
"""

from __future__ import annotations

import math

import torch

from relight_core.errors import InputError

MAX_PITCH_DEG = 90.0
MAX_ROLL_DEG = 180.0


def _angle(value, name: str, limit: float) -> float:
    try:
        degrees = float(value)
    except (TypeError, ValueError):
        degrees = math.nan
    if not (math.isfinite(degrees) and abs(degrees) <= limit):
        raise InputError(f"The camera {name} {value} is out of range; use a number of degrees from "
                         f"-{limit:g} to {limit:g}.")
    return degrees


def camera_rotation(pitch: float = 0.0, roll: float = 0.0) -> torch.Tensor:
    """The camera-to-world rotation [3, 3] (float32) of a camera tilted by `pitch` and `roll` degrees."""
    p = math.radians(_angle(pitch, "pitch", MAX_PITCH_DEG))
    r = math.radians(_angle(roll, "roll", MAX_ROLL_DEG))
    cp, sp, cr, sr = math.cos(p), math.sin(p), math.cos(r), math.sin(r)
    pitch_x = torch.tensor([[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]], dtype=torch.float64)
    roll_z = torch.tensor([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return (pitch_x @ roll_z).float()
