"""MIT multi-illumination loader on a fixture rendered with Mitsuba and laid out like the dataset."""

import json
import math
import shutil

import cv2
import numpy as np
import pytest
import torch
from PIL import Image

pytest.importorskip("mitsuba")

from relight_core import lighting  # noqa: E402
from relight_core.colour import linear_to_srgb  # noqa: E402
from relight_core.data import mit  # noqa: E402
from relight_core.data.probes import ProbeChoice  # noqa: E402
from relight_core.data.render import SceneRenderer, init_mitsuba  # noqa: E402
from relight_core.data.scenes import CameraSpec, MaterialSpec, ObjectSpec, SceneSpec, camera_to_world  # noqa: E402
from relight_core.errors import InputError  # noqa: E402

SIZE, BALL = 64, 32  # photo side (stands in for mip 2) and chrome crop side
SUNS = {0: (0.5, 0.5, 0.7), 12: (-0.6, 0.4, 0.7)}  # camera-frame sun direction per lighting


def _material(color, metallic, roughness):
    return MaterialSpec(base_color=color, texture=None, texture_repeat=1.0, roughness=roughness,
                        metallic=metallic, specular=0.5, transmission=0.0)


@pytest.fixture(scope="module")
def mit_root(tmp_path_factory):
    """One scene, lightings 0 and 12: a chrome ball on a grey floor under a small bright sun."""
    init_mitsuba(threads=1)
    radius, fov, distance = 0.3, 20.0, 3.0
    chrome = ObjectSpec("sphere", 0, (radius,) * 3, (0.0, 0.0), 0.0, 0.0, (0.0, 0.0), radius,
                        _material((1.0, 1.0, 1.0), 1.0, 0.02))
    camera = CameraSpec(target=(0.0, radius, 0.0), distance=distance, elevation=5.0, azimuth=0.0, fov=fov,
                        orbit=0.0, oscillation=0.0, cycles=1.0)
    choice = ProbeChoice("fixture", 0, 0.0, 1.0)
    spec = SceneSpec("test", 0, 0, 1, (), _material((0.5, 0.5, 0.5), 0.0, 0.8), (chrome,), (choice, choice),
                     0.0, camera)
    c2w = camera_to_world(spec, 0)
    probes = []
    for sun_camera in SUNS.values():
        sun = c2w @ (np.array(sun_camera) / np.linalg.norm(sun_camera))
        probe = np.full((64, 128, 3), 0.05, np.float32)
        probe[lighting.texel_directions(64, 128).numpy() @ sun > math.cos(math.radians(8))] = 50.0
        probes.append(probe)
    root = tmp_path_factory.mktemp("mit")
    scene = root / "fixture_kitchen1"
    (scene / "probes").mkdir(parents=True)
    # Ball bounding box in pixels (centred: the camera looks at the ball's centre).
    r_pix = math.tan(math.asin(radius / distance)) / math.tan(math.radians(fov / 2)) * SIZE / 2
    x0 = y0 = SIZE / 2 - r_pix
    with SceneRenderer(spec, SIZE, spp=16, probes=probes) as renderer:
        for light, direction in enumerate(SUNS):
            photo = linear_to_srgb(np.clip(renderer.render(0, light, seed=3), 0, 1))
            cv2.imwrite(str(scene / f"dir_{direction}_mip2.jpg"), (photo[..., ::-1] * 255).round().astype(np.uint8),
                        [cv2.IMWRITE_JPEG_QUALITY, 95])
            crop = photo[int(round(y0)):int(round(y0 + 2 * r_pix)), int(round(x0)):int(round(x0 + 2 * r_pix))]
            ball = cv2.resize(crop, (BALL, BALL), interpolation=cv2.INTER_AREA)
            cv2.imwrite(str(scene / "probes" / f"dir_{direction}_chrome{BALL}.jpg"),
                        (ball[..., ::-1] * 255).round().astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 95])
    Image.fromarray(np.zeros((SIZE, SIZE), np.uint8), mode="P").save(scene / "materials_mip2.png")
    # meta.json coordinates are mip-0 pixels; our 64² photo stands in for the 6000×4000 original.
    sx, sy = mit.FULL_SIZE[1] / SIZE, mit.FULL_SIZE[0] / SIZE
    box = {"x": x0 * sx, "y": y0 * sy, "w": 2 * r_pix * sx, "h": 2 * r_pix * sy}
    (scene / "meta.json").write_text(json.dumps({"chrome": {"bounding_box": box}}))
    return root


def _peak_direction(panorama: np.ndarray) -> np.ndarray:
    """Camera-frame direction (env_dir) of the centroid of the brightest panorama pixels."""
    env_dir = lighting.encode_lighting(torch.from_numpy(panorama)[None])["env_dir"][0].numpy()
    luminance = panorama.mean(-1)
    bright = luminance >= 0.9 * luminance.max()
    d = (env_dir[bright] * luminance[bright, None]).sum(0)
    return d / np.linalg.norm(d)


def test_layout_scenes_and_protocol_pairs(mit_root):
    scenes = mit.list_scenes(mit_root)
    assert [s.name for s in scenes] == ["fixture_kitchen1"]
    assert mit.directions(scenes[0]) == [0, 12]
    assert mit.protocol_pairs([0, 12]) == [(0, 12)]
    assert mit.protocol_pairs(list(range(25))) == [(i, i + 12) for i in range(13)]
    with pytest.raises(InputError, match="download"):
        mit.list_scenes(mit_root / "fixture_kitchen1" / "probes")


@pytest.mark.parametrize("direction", [0, 12])
def test_chrome_ball_becomes_a_camera_frame_probe_with_the_sun_in_place(mit_root, direction):
    scene = mit.list_scenes(mit_root)[0]
    ball = mit.load_chrome(scene, direction, size=BALL)
    found = _peak_direction(mit.chrome_to_panorama(ball, 32, 64))
    sun = np.array(SUNS[direction]) / np.linalg.norm(SUNS[direction])
    assert math.degrees(math.acos(np.clip(found @ sun, -1, 1))) < 15.0


def test_chrome_crop_from_meta_bounding_box_matches_the_probe_file(mit_root, tmp_path):
    scene = tmp_path / "scene"
    shutil.copytree(mit.list_scenes(mit_root)[0], scene)
    from_file = mit.load_chrome(scene, 0, size=BALL)
    shutil.rmtree(scene / "probes")
    from_meta = mit.load_chrome(scene, 0, size=BALL)
    assert from_meta.shape == from_file.shape
    assert np.abs(from_meta - from_file).mean() < 0.05


def test_probe_mask_covers_the_ball_only(mit_root):
    mask = mit.probe_mask(mit.list_scenes(mit_root)[0], SIZE, SIZE)
    assert mask[SIZE // 2, SIZE // 2] == 0 and mask[2, 2] == 1 and mask[SIZE - 3, 2] == 1
    assert 0.1 < 1 - mask.mean() < 0.5


def test_dataset_yields_pairs_in_the_training_format(mit_root):
    dataset = mit.MITMultiIllumination(mit_root, probe_size=BALL, size=48)
    assert len(dataset) == 1
    item = dataset[0]
    for key in ("input", "relit", "albedo", "env_ldr", "env_log", "env_dir"):
        assert item[key].shape == (3, 1, 48, 48), key
    assert item["mask"].shape == (1, 1, 48, 48)
    assert not bool(item["has_albedo"]) and bool(item["has_lighting"])
    assert not torch.equal(item["input"], item["relit"])
