"""HDR probes for the data engine: the bundled library and procedural skies, studios and nights.

All probes are lat-long arrays float32 [h, w, 3] in the project convention (DESIGN.md §3),
linear radiance. Run `python -m relight_core.data.probes` to regenerate the procedural EXRs
bundled in `envmaps/`.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from relight_core import colour, lighting
from relight_core.data.files import write_exr

ENVMAP_DIR = Path(__file__).resolve().parents[2] / "envmaps"
POLYHAVEN = ("city", "courtyard", "forest", "interior", "night", "studio", "sunrise", "sunset")
BUNDLED_PROCEDURAL = ("procedural_sky_noon", "procedural_studio", "procedural_sky_dusk",
                      "procedural_gels")
# The held-out test split lights its scenes only with these; train never sees them.
TEST_PROBES = ("forest", "sunset", "procedural_sky_dusk", "procedural_gels")
PROCEDURAL_KINDS = ("sun_sky", "studio", "gels", "night")
# Eleven more real HDRIs in envmaps/extra/ (CC0, envmaps/extra/README.md), for the train split of the "extended"
# library only: none is within a 0.75 correlation of a held-out probe (or of a bundled train one) at any yaw.
EXTRA_PROBES = ("apartment", "bridge", "esplanade", "hall", "lab", "lobby", "night", "sky", "studio", "warehouse",
                "workshop")
# "classic": the probes every dataset before 2026-12-07 was drawn from (its seeds give the same scenes as then);
# "extended": classic + the extra HDRIs for the train split (the test split is the same in both).
PROBE_LIBRARIES = ("classic", "extended")
DARK_SOURCES = ("file:night", "file:extra/night", "procedural:night")  # their exposure is drawn lower


@dataclass(frozen=True)
class ProbeChoice:
    """Which probe lights a scene: a bundled file or a procedural kind with its seed."""

    source: str         # "file:<name>" or "procedural:<kind>"
    seed: int           # procedural parameters are drawn from this seed
    rotation: float     # world yaw of the probe at frame 0, degrees
    exposure: float     # radiance of a white Lambertian patch under the normalised probe


def probe_names(split: str, library: str = "classic") -> list[str]:
    """Probe sources available to a split ('train' or 'test') in a library ('classic' or 'extended')."""
    if library not in PROBE_LIBRARIES:
        raise ValueError(f"unknown probe library {library!r}; one of {', '.join(PROBE_LIBRARIES)}")
    files = [n for n in POLYHAVEN + BUNDLED_PROCEDURAL if (n in TEST_PROBES) == (split == "test")]
    sources = [f"file:{n}" for n in files]
    if split == "train":
        sources += [f"procedural:{k}" for k in PROCEDURAL_KINDS]
        if library == "extended":
            sources += [f"file:extra/{n}" for n in EXTRA_PROBES]
    return sources


def load_choice(choice: ProbeChoice, height: int = 128) -> np.ndarray:
    """The probe of a choice, exposure-normalised, float32 [h, 2h, 3] (files keep their size; "file:extra/NAME"
    is envmaps/extra/NAME.exr)."""
    kind, name = choice.source.split(":", 1)
    if kind == "file":
        probe = lighting.load_probe(ENVMAP_DIR / f"{name}.exr").numpy()
    else:
        probe = procedural_probe(name, np.random.default_rng(choice.seed), height, 2 * height)
    return normalise_exposure(probe, choice.exposure)


# ---------------------------------------------------------------- exposure

def white_patch_radiance(probe: np.ndarray) -> float:
    """Mean radiance of a white Lambertian patch facing up, ±x and ±z (E/π averaged)."""
    h, w, _ = probe.shape
    d = _texel_directions(h, w)
    theta = (np.arange(h) + 0.5) / h * np.pi
    solid_angle = (2 * np.pi / w) * (np.pi / h) * np.sin(theta)[:, None]  # [h, 1]
    normals = np.array([[0, 1, 0], [1, 0, 0], [-1, 0, 0], [0, 0, 1], [0, 0, -1]], np.float32)
    luminance = colour.luminance(probe)  # [h, w]
    cosines = np.clip(d @ normals.T, 0, None)  # [h, w, 5]
    irradiance = np.einsum("hw,hwn,hw->n", luminance, cosines, np.broadcast_to(solid_angle, (h, w)))
    return float(irradiance.mean() / np.pi)


def normalise_exposure(probe: np.ndarray, exposure: float) -> np.ndarray:
    """Scale a probe so a white Lambertian patch under it has radiance `exposure` on average."""
    return probe * (exposure / max(white_patch_radiance(probe), 1e-8))


def _texel_directions(height: int, width: int) -> np.ndarray:
    """Unit directions of a lat-long file's texel centres, float32 [h, w, 3]."""
    return lighting.texel_directions(height, width).numpy()


# ---------------------------------------------------------------- procedural probes

def procedural_probe(kind: str, rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A random probe of one procedural kind ('sun_sky', 'studio', 'gels', 'night')."""
    if kind == "sun_sky":
        return sun_sky(height, width, elevation=rng.uniform(5, 75), azimuth=rng.uniform(-180, 180),
                       turbidity=rng.uniform(2, 8))
    if kind == "studio":
        return studio(height, width, rng, saturation=0.1)
    if kind == "gels":
        return studio(height, width, rng, saturation=0.8)
    if kind == "night":
        return night(height, width, rng)
    raise ValueError(f"unknown procedural probe kind {kind!r}")


def sun_direction(elevation: float, azimuth: float) -> np.ndarray:
    """Unit direction at `elevation` above the horizon and `azimuth` = atan2(x, −z), degrees."""
    el, az = np.radians(elevation), np.radians(azimuth)
    return np.array([np.cos(el) * np.sin(az), np.sin(el), -np.cos(el) * np.cos(az)], np.float32)


def sun_sky(height: int, width: int, elevation: float, azimuth: float, turbidity: float,
            sun_radius: float = 1.5) -> np.ndarray:
    """Analytic clear sky (Preetham et al. 1999) with a sun disc and a grey ground, linear RGB."""
    d = _texel_directions(height, width)
    sun = sun_direction(elevation, azimuth)
    theta_s = np.pi / 2 - np.radians(elevation)
    theta = np.arccos(np.clip(d[..., 1], 0.01, 1.0))  # the sky model is defined above the horizon
    gamma = np.arccos(np.clip(d @ sun, -1.0, 1.0))
    t = turbidity
    # Perez distribution coefficients (A..E) for luminance Y and chromaticities x, y.
    coeff_Y = (0.1787 * t - 1.4630, -0.3554 * t + 0.4275, -0.0227 * t + 5.3251,
               0.1206 * t - 2.5771, -0.0670 * t + 0.3703)
    coeff_x = (-0.0193 * t - 0.2592, -0.0665 * t + 0.0008, -0.0004 * t + 0.2125,
               -0.0641 * t - 0.8989, -0.0033 * t + 0.0452)
    coeff_y = (-0.0167 * t - 0.2608, -0.0950 * t + 0.0092, -0.0079 * t + 0.2102,
               -0.0441 * t - 1.6537, -0.0109 * t + 0.0529)

    def perez(theta_, gamma_, c):
        a, b, cc, dd, e = c
        return (1 + a * np.exp(b / np.cos(theta_))) * (1 + cc * np.exp(dd * gamma_)
                                                      + e * np.cos(gamma_) ** 2)

    chi = (4.0 / 9.0 - t / 120.0) * (np.pi - 2 * theta_s)
    zenith_Y = (4.0453 * t - 4.9710) * np.tan(chi) - 0.2155 * t + 2.4192  # kcd/m²
    ts = np.array([theta_s**3, theta_s**2, theta_s, 1.0])
    tt = np.array([t * t, t, 1.0])
    zenith_x = tt @ np.array([[0.00166, -0.00375, 0.00209, 0.0],
                              [-0.02903, 0.06377, -0.03202, 0.00394],
                              [0.11693, -0.21196, 0.06052, 0.25886]]) @ ts
    zenith_y = tt @ np.array([[0.00275, -0.00610, 0.00317, 0.0],
                              [-0.04214, 0.08970, -0.04153, 0.00516],
                              [0.15346, -0.26756, 0.06670, 0.26688]]) @ ts
    Y = zenith_Y * perez(theta, gamma, coeff_Y) / perez(0.0, theta_s, coeff_Y)
    x = zenith_x * perez(theta, gamma, coeff_x) / perez(0.0, theta_s, coeff_x)
    y = zenith_y * perez(theta, gamma, coeff_y) / perez(0.0, theta_s, coeff_y)
    sky = _xyY_to_rgb(x, y, np.maximum(Y, 0.0))

    # Sun: extraterrestrial illuminance attenuated by Rayleigh + Angstrom aerosol optical depth.
    airmass = 1.0 / (np.cos(theta_s) + 0.15 * (93.885 - np.degrees(theta_s)) ** -1.253)
    wavelengths = np.array([0.65, 0.55, 0.45])  # µm, for R, G, B
    beta = 0.04608 * t - 0.04586
    tau = 0.008735 * wavelengths**-4.08 + beta * wavelengths**-1.3
    sun_illuminance = 120.0 * np.exp(-airmass * tau)  # klx per channel
    radius = np.radians(sun_radius)
    disc_solid_angle = 2 * np.pi * (1 - np.cos(radius))
    # A soft rim (one probe pixel wide) keeps the tiny disc from aliasing at low resolution.
    rim = np.radians(180.0 / height)
    disc = np.clip((radius + rim / 2 - gamma) / rim, 0, 1)[..., None]
    sky = sky + disc * (sun_illuminance / disc_solid_angle)

    # Ground: grey Lambertian lit by the sky and sun above it.
    above = d[..., 1:2] > 0
    ground_albedo = 0.25
    upper = np.where(above, sky, 0.0)
    h, w = height, width
    solid_angle = ((2 * np.pi / w) * (np.pi / h) * np.sin((np.arange(h) + 0.5) / h * np.pi))
    irradiance = np.einsum("hwc,hw,h->c", upper, np.clip(d[..., 1], 0, None), solid_angle)
    ground = ground_albedo * irradiance / np.pi
    return np.where(above, sky, ground).astype(np.float32)


def studio(height: int, width: int, rng: np.random.Generator, saturation: float) -> np.ndarray:
    """Dim grey room with 2–4 soft rectangular area lights; `saturation` tints them (gels)."""
    d = _texel_directions(height, width)
    wall = 0.05 + 0.05 * np.clip(d[..., 1:2], -0.5, 1.0)  # slightly brighter ceiling
    probe = np.broadcast_to(wall, d.shape).copy() * _random_color(rng, 0.05)
    for _ in range(int(rng.integers(2, 5))):
        centre = sun_direction(rng.uniform(5, 65), rng.uniform(-180, 180))
        tangent = np.cross(centre, [0.0, 1.0, 0.0])
        tangent /= np.linalg.norm(tangent)
        bitangent = np.cross(tangent, centre)
        z = d @ centre
        a = np.arctan2(d @ tangent, z)
        b = np.arctan2(d @ bitangent, z)
        half_w, half_h = np.radians(rng.uniform(8, 25)), np.radians(rng.uniform(8, 25))
        soft = np.radians(3.0)
        inside = (np.clip((half_w - np.abs(a)) / soft + 0.5, 0, 1)
                  * np.clip((half_h - np.abs(b)) / soft + 0.5, 0, 1) * (z > 0))
        power = rng.uniform(5, 40)
        probe += inside[..., None] * power * _random_color(rng, saturation)
    return probe.astype(np.float32)


def night(height: int, width: int, rng: np.random.Generator) -> np.ndarray:
    """Dark blue sky, a moon, sodium street lamps near the horizon and a dark ground."""
    d = _texel_directions(height, width)
    up = d[..., 1:2]
    sky = np.where(up > 0, 0.02 + 0.03 * (1 - up), 0.004) * np.array([0.35, 0.5, 1.0], np.float32)
    moon = sun_direction(rng.uniform(15, 70), rng.uniform(-180, 180))
    moon_disc = np.clip((np.radians(3.0) - np.arccos(np.clip(d @ moon, -1, 1))) / 0.02, 0, 1)
    sky = sky + moon_disc[..., None] * np.array([1.5, 1.6, 1.8], np.float32) * rng.uniform(3, 8)
    for _ in range(int(rng.integers(2, 7))):
        lamp = sun_direction(rng.uniform(-2, 12), rng.uniform(-180, 180))
        glow = np.exp((d @ lamp - 1.0) / 0.0015)
        color = np.array([1.0, 0.55, 0.15], np.float32) if rng.random() < 0.7 else np.ones(3)
        sky = sky + glow[..., None] * color * rng.uniform(5, 20)
    return sky.astype(np.float32)


def _random_color(rng: np.random.Generator, saturation: float) -> np.ndarray:
    """A random hue at the given saturation, unit luminance-ish linear RGB."""
    hue = rng.uniform(0, 1)
    rgb = np.clip(np.abs(((hue * 6 + np.array([0, 4, 2])) % 6) - 3) - 1, 0, 1)
    return ((1 - saturation) + saturation * rgb).astype(np.float32)


def _xyY_to_rgb(x: np.ndarray, y: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """CIE xyY → linear sRGB (D65), negatives clipped."""
    y = np.maximum(y, 1e-6)
    X, Z = x / y * Y, (1 - x - y) / y * Y
    xyz = np.stack([X, Y, Z], axis=-1)
    m = np.array([[3.2406, -1.5372, -0.4986],
                  [-0.9689, 1.8758, 0.0415],
                  [0.0557, -0.2040, 1.0570]], np.float32)
    return np.clip(xyz @ m.T, 0.0, None)


def bundled_procedural(name: str, height: int = 256) -> np.ndarray:
    """The fixed procedural probes shipped in envmaps/ (two train, two held out for test)."""
    w = 2 * height
    if name == "procedural_sky_noon":
        return sun_sky(height, w, elevation=60.0, azimuth=30.0, turbidity=2.5)
    if name == "procedural_sky_dusk":
        return sun_sky(height, w, elevation=6.0, azimuth=-120.0, turbidity=6.0)
    if name == "procedural_studio":
        return studio(height, w, np.random.default_rng(7), saturation=0.05)
    if name == "procedural_gels":
        return studio(height, w, np.random.default_rng(11), saturation=0.9)
    raise ValueError(f"unknown bundled procedural probe {name!r}")


def main() -> None:
    """Write the bundled procedural probes as half-float EXRs."""
    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--out", type=Path, default=ENVMAP_DIR)
    args = parser.parse_args()
    for name in BUNDLED_PROCEDURAL:
        write_exr(args.out / f"{name}.exr", bundled_procedural(name))
        print(f"wrote {args.out / name}.exr")


if __name__ == "__main__":
    main()
