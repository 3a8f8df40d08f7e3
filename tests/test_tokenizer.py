"""Tokenizer contract: shapes, frame/size checks, causality, sigma_data scaling, weights, JIT loading."""

from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from safetensors.torch import save_file

from relight_core.errors import InputError
from relight_core.tokenizer import (
    TOKENIZER_PRESETS,
    CausalVideoAutoencoder,
    CosmosJITTokenizer,
    Tokenizer,
    TokenizerConfig,
    build_tokenizer,
    check_frames,
    latent_frames,
    tokenizer_loss,
)
from tests.factory import FakeCosmosDecoder, FakeCosmosEncoder

H, W = 32, 48


def video(frames: int, batch: int = 1, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(batch, 3, frames, H, W, generator=generator) * 2 - 1  # (B, 3, T, H, W)


def random_autoencoder(**overrides) -> CausalVideoAutoencoder:
    """Tiny model with every weight random, so zero-initialised paths cannot hide leaks."""
    torch.manual_seed(0)
    model = CausalVideoAutoencoder(TokenizerConfig(**{**vars(TOKENIZER_PRESETS["tiny"]), **overrides}))
    with torch.no_grad():
        for parameter in model.parameters():
            parameter.normal_(0.0, 0.3)
    return model.eval()


# --- shapes and checks ---------------------------------------------------------------------------


@pytest.mark.parametrize("frames, expected", [(1, 1), (9, 2), (17, 3)])
def test_causal_ae_shapes(frames, expected):
    model = random_autoencoder()
    latents = model.encode(video(frames, batch=2))
    assert latents.shape == (2, 16, expected, H // 8, W // 8)
    assert model.latent_frames(frames) == expected
    decoded = model.decode(latents)
    assert decoded.shape == (2, 3, frames, H, W)
    assert decoded.min() >= -1 and decoded.max() <= 1


@pytest.mark.parametrize("factor", [1, 2, 4])
def test_other_temporal_factors(factor):
    model = random_autoencoder(temporal_factor=factor)
    frames = 1 + 2 * factor
    latents = model.encode(video(frames))
    assert latents.shape == (1, 16, 3, H // 8, W // 8)
    assert model.decode(latents).shape == (1, 3, frames, H, W)


def test_protocol_and_latent_frames():
    model = random_autoencoder()
    assert isinstance(model, Tokenizer)
    assert (model.spatial_factor, model.temporal_factor, model.latent_channels) == (8, 8, 16)
    assert [latent_frames(t, 8) for t in (1, 9, 17, 57)] == [1, 2, 3, 8]


@pytest.mark.parametrize("frames, suggestion", [(8, "1 or 9"), (10, "9 or 17"), (0, "1 or 9")])
def test_bad_frame_count_is_one_clear_sentence(frames, suggestion):
    with pytest.raises(InputError) as error:
        check_frames(frames, 8)
    assert str(error.value) == (
        f"A clip of {frames} frames cannot be tokenized: use 1 + k·8 frames (e.g. {suggestion})."
    )
    if frames:
        with pytest.raises(InputError, match=f"{frames} frames"):
            random_autoencoder().encode(video(frames))


def test_bad_size_and_shape():
    model = random_autoencoder()
    with pytest.raises(InputError, match="multiples of 16"):
        model.encode(torch.zeros(1, 3, 9, 40, 48))
    with pytest.raises(InputError, match="multiples of 16"):
        model.encode(torch.zeros(1, 3, 9, 32, 8))
    with pytest.raises(InputError, match=r"\[B,3,T,H,W\]"):
        model.encode(torch.zeros(3, 9, 32, 48))


def test_bad_config_rejected():
    with pytest.raises(InputError, match="1, 2, 4 or 8"):
        TokenizerConfig(temporal_factor=3)


# --- causality -----------------------------------------------------------------------------------


@pytest.mark.parametrize("factor", [8, 2])
def test_encoder_is_causal(factor):
    model = random_autoencoder(temporal_factor=factor)
    clip = video(1 + 2 * factor)
    changed_frame = factor + 1  # First frame of latent frame 2.
    edited = clip.clone()
    edited[:, :, changed_frame] = -edited[:, :, changed_frame]
    before, after = model.encode(clip), model.encode(edited)
    torch.testing.assert_close(after[:, :, :2], before[:, :, :2], rtol=0, atol=0)
    assert not torch.allclose(after[:, :, 2], before[:, :, 2])


def test_decoder_is_causal():
    model = random_autoencoder()
    latents = model.encode(video(17))
    edited = latents.clone()
    edited[:, :, 2] += 1.0
    before, after = model.decode(latents), model.decode(edited)
    torch.testing.assert_close(after[:, :, :9], before[:, :, :9], rtol=0, atol=0)
    assert not torch.allclose(after[:, :, 9:], before[:, :, 9:])


def test_image_is_first_latent_frame():
    model = random_autoencoder()
    clip = video(17)
    image_latent = model.encode(clip[:, :, :1])
    assert image_latent.shape == (1, 16, 1, H // 8, W // 8)
    torch.testing.assert_close(image_latent, model.encode(clip)[:, :, :1], rtol=1e-5, atol=1e-5)


# --- sigma_data, training, weights -----------------------------------------------------------------


def test_causal_ae_sigma_data_scaling():
    model = random_autoencoder()
    clip = video(9)
    mean, _ = model.posterior(clip)
    torch.testing.assert_close(model.encode(clip), 0.5 * mean)
    latents = torch.randn(1, 16, 2, H // 8, W // 8)
    torch.testing.assert_close(model.decode(latents), model.decode_raw(latents / 0.5).clamp(-1, 1))


def test_training_reduces_loss():
    torch.manual_seed(0)
    model = CausalVideoAutoencoder(TOKENIZER_PRESETS["tiny"]).train()
    # A smooth clip: white noise would be incompressible at 8×8×8.
    clip = F.interpolate(video(9)[:, :, :, :4, :4], size=(9, 16, 32), mode="trilinear")
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-2)
    first = tokenizer_loss(model, clip)
    assert set(first) == {"loss", "l1", "kl"}
    for _ in range(25):
        optimizer.zero_grad()
        tokenizer_loss(model, clip)["loss"].backward()
        optimizer.step()
    assert tokenizer_loss(model, clip)["l1"] < 0.7 * first["l1"]


def test_safetensors_round_trip(tmp_path: Path):
    model = random_autoencoder(temporal_factor=4)
    save_file(model.state_dict(), tmp_path / "tokenizer.safetensors")
    spec = {"type": "causal-ae", "preset": "tiny", "temporal_factor": 4, "weights": "tokenizer.safetensors"}
    loaded = build_tokenizer(spec, tmp_path)
    assert isinstance(loaded, CausalVideoAutoencoder) and loaded.temporal_factor == 4
    clip = video(9)
    assert torch.equal(loaded.encode(clip), model.encode(clip))
    assert not torch.equal(build_tokenizer({"type": "causal-ae", "preset": "tiny", "temporal_factor": 4}).encode(clip), model.encode(clip))


def test_build_errors(tmp_path: Path):
    with pytest.raises(InputError, match="missing.safetensors"):
        build_tokenizer({"type": "causal-ae", "preset": "tiny", "weights": "missing.safetensors"}, tmp_path)
    with pytest.raises(InputError, match="'huge'"):
        build_tokenizer({"type": "causal-ae", "preset": "huge"}, tmp_path)
    with pytest.raises(InputError, match="width"):
        build_tokenizer({"type": "causal-ae", "preset": "tiny", "width": 3}, tmp_path)
    with pytest.raises(InputError, match="'vqgan'"):
        build_tokenizer({"type": "vqgan"}, tmp_path)


# --- Cosmos TorchScript loader ---------------------------------------------------------------------


@pytest.fixture
def cosmos_files(tmp_path: Path) -> Path:
    torch.manual_seed(0)
    torch.jit.script(FakeCosmosEncoder()).save(str(tmp_path / "encoder.jit"))
    torch.jit.script(FakeCosmosDecoder()).save(str(tmp_path / "decoder.jit"))
    return tmp_path


def test_cosmos_jit_sigma_data_scaling(cosmos_files: Path):
    tokenizer = CosmosJITTokenizer(cosmos_files / "encoder.jit", cosmos_files / "decoder.jit", dtype=torch.float32)
    assert isinstance(tokenizer, Tokenizer)
    encoder = torch.jit.load(str(cosmos_files / "encoder.jit"))
    decoder = torch.jit.load(str(cosmos_files / "decoder.jit"))
    clip = video(17, batch=3)
    latents = tokenizer.encode(clip)
    assert latents.shape == (3, 16, 3, H // 8, W // 8)
    assert torch.equal(latents, 0.5 * encoder(clip)[0])
    decoded = tokenizer.decode(latents)
    assert decoded.shape == (3, 3, 17, H, W)
    assert torch.equal(decoded, decoder(latents / 0.5).clamp(-1, 1))
    assert tokenizer.encode(clip[:, :, :1]).shape == (3, 16, 1, H // 8, W // 8)


def test_cosmos_jit_splits_batch_and_runs_bf16(cosmos_files: Path):
    exact = CosmosJITTokenizer(cosmos_files / "encoder.jit", cosmos_files / "decoder.jit", dtype=torch.float32)
    bf16 = CosmosJITTokenizer(cosmos_files / "encoder.jit", cosmos_files / "decoder.jit", max_batch=2)
    clip = video(9, batch=3)
    latents = bf16.encode(clip)
    assert latents.dtype == torch.float32 and latents.shape == (3, 16, 2, H // 8, W // 8)
    torch.testing.assert_close(latents, exact.encode(clip), rtol=0.05, atol=0.02)
    assert bf16.decode(latents).dtype == torch.float32
    with pytest.raises(InputError, match="10 frames"):
        bf16.encode(video(10))


def test_cosmos_jit_latent_statistics(cosmos_files: Path):
    mean, std = torch.randn(16, 4), torch.rand(16, 4) + 0.5  # Per channel, per latent frame.
    image_mean, image_std = torch.randn(16), torch.rand(16) + 0.5
    torch.save((mean.flatten(), std.flatten()), cosmos_files / "mean_std.pt")
    torch.save((image_mean, image_std), cosmos_files / "image_mean_std.pt")
    spec = {"type": "cosmos-jit", "encoder": "encoder.jit", "decoder": "decoder.jit", "dtype": "float32",
            "mean_std": "mean_std.pt", "image_mean_std": "image_mean_std.pt"}
    tokenizer = build_tokenizer(spec, cosmos_files)
    encoder = torch.jit.load(str(cosmos_files / "encoder.jit"))
    clip = video(17)
    expected = (encoder(clip)[0] - mean[:, :3].reshape(1, 16, 3, 1, 1)) / std[:, :3].reshape(1, 16, 3, 1, 1)
    torch.testing.assert_close(tokenizer.encode(clip), 0.5 * expected)
    image = clip[:, :, :1]
    expected_image = (encoder(image)[0] - image_mean.reshape(1, 16, 1, 1, 1)) / image_std.reshape(1, 16, 1, 1, 1)
    torch.testing.assert_close(tokenizer.encode(image), 0.5 * expected_image)
    # decode undoes the normalisation before the decoder.
    decoder = torch.jit.load(str(cosmos_files / "decoder.jit"))
    torch.testing.assert_close(tokenizer.decode(tokenizer.encode(clip)), decoder(encoder(clip)[0]).clamp(-1, 1))
    with pytest.raises(InputError, match="at most 25 frames"):
        tokenizer.encode(video(33))


def test_cosmos_jit_missing_file(cosmos_files: Path):
    (cosmos_files / "decoder.jit").unlink()
    with pytest.raises(InputError, match="decoder.jit"):
        build_tokenizer({"type": "cosmos-jit", "encoder": "encoder.jit", "decoder": "decoder.jit"}, cosmos_files)
    with pytest.raises(InputError, match="decoder.jit"):
        CosmosJITTokenizer(cosmos_files / "encoder.jit", cosmos_files / "decoder.jit")
    with pytest.raises(InputError, match="mean_std.pt"):
        build_tokenizer({"type": "cosmos-jit", "mean_std": "mean_std.pt"}, cosmos_files)
