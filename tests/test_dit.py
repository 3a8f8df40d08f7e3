"""The joint DiT: channel layout, input assembly, RoPE, forward shapes, checkpoints and the 7B map."""

import dataclasses

import pytest
import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save_file

from relight_core.dit import (
    ASSEMBLED_CHANNELS, CHANNELS, DIT_PRESETS, LIGHTING_CHANNELS, TOKEN_CHANNELS, DiTConfig, JointDiT,
    assemble_inputs, pack_lighting, param_count,
)
from relight_core.released import convert_released_state_dict, released_to_ours
from relight_core.rope import rms_norm_rope, rope_angles

TINY = DIT_PRESETS["tiny"]


@pytest.fixture(autouse=True)
def no_grad():
    with torch.no_grad():
        yield


def randomised(model: JointDiT, seed: int = 0) -> JointDiT:
    """Give every parameter random values so zero-initialised paths are exercised."""
    generator = torch.Generator().manual_seed(seed)
    for p in model.parameters():
        p.copy_(torch.randn(p.shape, generator=generator) * 0.2)
    return model


def reference_rms_norm(x: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Plain fp32 RMSNorm over the last dim, eps 1e-6."""
    x = x.float()
    return x * torch.rsqrt(x.pow(2).mean(-1, keepdim=True) + 1e-6) * weight.float()


def reference_rope(x: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """Plain fp32 rotation of dims i and i + hd/2 by the half-angle tables cos, sin (broadcast to x)."""
    x1, x2 = x.float().chunk(2, dim=-1)
    return torch.cat([x1 * cos - x2 * sin, x2 * cos + x1 * sin], dim=-1)


def reference_forward(model: JointDiT, x: torch.Tensor, c_noise: torch.Tensor) -> torch.Tensor:
    """The DiT forward written out plainly in fp32 (no fused ops), from the model's own parameters."""
    c = model.config
    _, _, frames, h, w = x.shape
    heads, p = c.num_heads, c.patch_spatial
    tokens = model.patch_embed(model.patchify(model.embed_inputs(x)))             # (B, L, D)
    cos, sin = model.rope(frames // 3, h // p, w // p, "cpu")                      # (L, hd/2)
    cos, sin = cos[:, None], sin[:, None]                                         # (L, 1, hd/2)
    emb, lora = model.t_embedder(c_noise)

    def modulated(x, shift, scale):
        return F.layer_norm(x, x.shape[-1:], eps=1e-6) * (1 + scale[:, None]) + shift[:, None]

    for block in model.blocks:
        attn = block.self_attn
        shift, scale, gate = block.self_attn_mod(emb, lora)
        a = modulated(tokens, shift, scale)
        q = reference_rope(reference_rms_norm(attn.q_proj(a).unflatten(-1, (heads, -1)), attn.q_norm.weight), cos, sin)
        k = reference_rope(reference_rms_norm(attn.k_proj(a).unflatten(-1, (heads, -1)), attn.k_norm.weight), cos, sin)
        v = attn.v_proj(a).unflatten(-1, (heads, -1))
        out = F.scaled_dot_product_attention(q.transpose(1, 2), k.transpose(1, 2), v.transpose(1, 2))
        tokens = tokens + gate[:, None] * attn.out_proj(out.transpose(1, 2).flatten(2))
        shift, scale, gate = block.mlp_mod(emb, lora)
        hidden = F.gelu(block.mlp.fc1(modulated(tokens, shift, scale)))
        tokens = tokens + gate[:, None] * block.mlp.fc2(hidden)
    shift, scale = model.final_layer.modulation(emb, lora)
    out = model.final_layer.linear(modulated(tokens, shift, scale))
    return model.unpatchify(out, frames, h, w)


# ---------------------------------------------------------------- token layout


def test_channels_are_the_documented_contiguous_layout():
    names = ["noisy", "condition_mask", "env_ldr", "env_ldr_mask", "env_log", "env_log_mask",
             "env_dir", "env_dir_mask", "padding_mask", "clip_type"]
    widths = [16, 1, 16, 1, 16, 1, 16, 1, 1, 3]
    assert list(CHANNELS) == names
    start = 0
    for name, width in zip(names, widths):
        assert CHANNELS[name] == slice(start, start + width), name
        start += width
    assert (start, ASSEMBLED_CHANNELS, TOKEN_CHANNELS, LIGHTING_CHANNELS) == (72, 69, 72, 51)


def test_pack_lighting_orders_latents_with_masks_and_zeroes_dropped_ones():
    ldr, log_, dir_ = (torch.full((1, 16, 2, 4, 4), v) for v in (1.0, 2.0, 3.0))
    packed = pack_lighting(ldr, log_, dir_)
    assert packed.shape == (1, 51, 2, 4, 4)
    offset = CHANNELS["env_ldr"].start
    for name, value in (("env_ldr", 1.0), ("env_log", 2.0), ("env_dir", 3.0)):
        lat = CHANNELS[name].start - offset
        assert bool((packed[:, lat:lat + 16] == value).all())
        assert bool((packed[:, lat + 16] == 1.0).all())
    dropped = pack_lighting(ldr, None, dir_)
    assert bool((dropped[:, 17:34] == 0).all())                   # env_log latent and its mask
    assert bool((dropped[:, 34:50] == 3.0).all())


def test_assemble_inputs_places_each_input_where_documented():
    b, t, h, w = 2, 2, 4, 6
    noisy = torch.randn(b, 16, 3 * t, h, w)
    cond_mask = torch.zeros(b, 1, 3 * t, 1, 1)
    cond_mask[:, :, :t] = 1.0
    lighting = torch.randn(b, 51, t, h, w)
    padding = torch.zeros(b, 1, 8 * h, 8 * w)
    padding[:, :, :, -8:] = 1.0                                   # the last latent column is padding
    x = assemble_inputs(noisy, cond_mask, lighting, padding)
    assert x.shape == (b, 69, 3 * t, h, w)
    assert torch.equal(x[:, CHANNELS["noisy"]], noisy)
    assert torch.equal(x[:, CHANNELS["condition_mask"]], cond_mask.expand(b, 1, 3 * t, h, w))
    light = x[:, CHANNELS["env_ldr"].start:CHANNELS["env_dir_mask"].stop]
    assert torch.equal(light[:, :, t:2 * t], lighting)            # relit clip
    assert bool((light[:, :, :t] == 0).all()) and bool((light[:, :, 2 * t:] == 0).all())
    pad = x[:, CHANNELS["padding_mask"]]
    assert bool((pad[..., -1] == 1).all()) and bool((pad[..., :-1] == 0).all())
    empty = assemble_inputs(noisy, cond_mask, None, None)
    assert bool((empty[:, CHANNELS["env_ldr"].start:] == 0).all())


def test_clip_type_embedding_is_per_clip():
    model = JointDiT(TINY)
    x = torch.randn(1, 69, 6, 4, 4)
    out = model.embed_inputs(x)
    assert out.shape == (1, 72, 6, 4, 4)
    assert torch.equal(out[:, :69], x)
    types = out[:, CHANNELS["clip_type"]]
    table = model.clip_type_embed.weight.detach()
    for clip in range(3):
        frames = types[:, :, 2 * clip:2 * clip + 2]
        assert torch.equal(frames, table[clip].view(1, 3, 1, 1, 1).expand_as(frames))
    assert not torch.equal(table[0], table[1])


# ---------------------------------------------------------------- rotary embedding


def test_rope_split_matches_released_rule_for_head_dim_128():
    angles = rope_angles(128, t=3, h=2, w=2)                     # (12, 128), [t 22 | h 21 | w 21] × 2
    grid = angles.view(3, 2, 2, 128)
    assert torch.equal(angles[:, :64], angles[:, 64:])
    t_part, h_part, w_part = grid[..., :22], grid[..., 22:43], grid[..., 43:64]
    assert torch.equal(t_part[:, 0], t_part[:, 1]) and not torch.equal(t_part[0], t_part[1])
    assert torch.equal(h_part[:, :, 0], h_part[:, :, 1]) and not torch.equal(h_part[:, 0], h_part[:, 1])
    assert torch.equal(w_part[:, 0], w_part[:, 1]) and not torch.equal(w_part[..., 0, :], w_part[..., 1, :])
    # base frequencies: θ = 10000 for h/w, NTK-scaled θ·2^(44/42) for t (extrapolation 2)
    assert float(h_part[0, 1, 0, 1]) == pytest.approx(10000.0 ** (-2 / 42), rel=1e-6)
    assert float(t_part[1, 0, 0, 1]) == pytest.approx((10000.0 * 2 ** (44 / 42)) ** (-2 / 44), rel=1e-6)


def test_rope_repeats_per_clip_and_separates_positions():
    model = JointDiT(TINY)
    t, h, w = 2, 3, 4
    cos, sin = model.rope(t, h, w, "cpu")
    per_clip = t * h * w
    assert cos.shape == (3 * per_clip, TINY.head_dim // 2)
    for clip in (1, 2):
        assert torch.equal(cos[clip * per_clip:(clip + 1) * per_clip], cos[:per_clip])
        assert torch.equal(sin[clip * per_clip:(clip + 1) * per_clip], sin[:per_clip])
    positions = torch.cat([cos[:per_clip], sin[:per_clip]], dim=1)
    assert torch.unique(positions, dim=0).shape[0] == per_clip   # every (t, h, w) differs


def test_rms_norm_rope_matches_norm_then_rotate_half_on_full_angles():
    angles = rope_angles(128, t=2, h=3, w=2)                     # (12, 128)
    weight = 1 + 0.3 * torch.randn(128)
    x = torch.randn(2, 12, 4, 128).transpose(1, 2)              # (B, heads, L, hd), strided like the model's
    normed = reference_rms_norm(x, weight)
    n1, n2 = normed.chunk(2, dim=-1)
    full = normed * angles.cos() + torch.cat([-n2, n1], dim=-1) * angles.sin()   # transformer_engine form
    half = angles[:, :64]
    out = rms_norm_rope(x, weight, half.cos(), half.sin())
    assert out.is_contiguous()                                  # the layout attention reads fastest
    torch.testing.assert_close(out, full, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(out, reference_rope(normed, half.cos(), half.sin()), rtol=1e-5, atol=1e-5)
    bf16 = rms_norm_rope(x.bfloat16(), weight.bfloat16(), half.cos(), half.sin())
    assert bf16.dtype == torch.bfloat16
    torch.testing.assert_close(bf16.float(), full, rtol=0.02, atol=0.03)


def test_attention_depends_only_on_relative_position_within_and_across_clips():
    # Shifting every clip's content by one latent frame leaves RoPE attention logits unchanged.
    cos, sin = JointDiT(TINY).rope(1, 1, 5, "cpu")              # (15, hd/2): 3 clips × 5 positions
    ones = torch.ones(TINY.head_dim)
    q, k = (rms_norm_rope(torch.randn(TINY.head_dim).expand(1, 1, 15, -1), ones, cos, sin)[0, 0]
            for _ in range(2))                                   # one vector at every position
    logit = lambda i, j: (q[i] * k[j]).sum()
    assert float(logit(1, 3)) == pytest.approx(float(logit(2, 4)), rel=1e-5)
    assert float(logit(1, 6)) == pytest.approx(float(logit(1, 1)), rel=1e-5)   # same spot, next clip


# ---------------------------------------------------------------- forward pass


@pytest.mark.parametrize("t", [1, 3])
def test_tiny_forward_shape(t):
    model = randomised(JointDiT(TINY))
    out = model(torch.randn(2, 69, 3 * t, 4, 6), torch.randn(2))
    assert out.shape == (2, 16, 3 * t, 4, 6)
    assert torch.isfinite(out).all()


@pytest.mark.parametrize("batch,t", [(1, 1), (2, 3)])
def test_forward_matches_plain_reference(batch, t):
    model = randomised(JointDiT(TINY))
    x, c_noise = torch.randn(batch, 69, 3 * t, 4, 6), torch.randn(batch)
    reference = reference_forward(model, x, c_noise)
    torch.testing.assert_close(model(x, c_noise), reference, rtol=1e-5, atol=1e-5)
    # bf16 weights under bf16 autocast, as the Relighter runs it, against the same weights in fp32
    half = model.to(torch.bfloat16)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        fast = half(x, c_noise).float()
    reference = reference_forward(half.float(), x, c_noise)
    assert float((fast - reference).norm() / reference.norm()) < 0.02


def test_output_is_zero_at_initialisation_and_blocks_start_as_identity():
    model = JointDiT(TINY)
    x = torch.randn(1, 69, 3, 4, 4)
    assert torch.equal(model(x, torch.tensor([0.3])), torch.zeros(1, 16, 3, 4, 4))
    tokens = torch.randn(1, 12, TINY.width)
    emb, lora = model.t_embedder(torch.tensor([0.3]))
    rope = model.rope(1, 2, 2, "cpu")
    assert torch.equal(model.blocks[0](tokens, emb, lora, rope), tokens)


def test_output_depends_on_noise_level_channels_and_other_clips():
    model = randomised(JointDiT(TINY))
    x = torch.randn(1, 69, 3, 4, 4)
    base = model(x, torch.tensor([0.1]))
    assert not torch.allclose(base, model(x, torch.tensor([1.0])))
    lit = x.clone()
    lit[:, CHANNELS["env_ldr"], 1] += 1.0                         # lighting on the relit clip
    changed = model(lit, torch.tensor([0.1]))
    assert not torch.allclose(changed[:, :, 2], base[:, :, 2])    # the albedo clip sees it (joint attention)


def test_patch_layout_matches_released_feature_order():
    model = JointDiT(TINY)
    x = torch.arange(72 * 2 * 2, dtype=torch.float32).view(1, 72, 1, 2, 2)
    features = model.patchify(x)                                  # (1, 1, 288), order (c, t, h, w)
    assert torch.equal(features[0, 0], x.flatten())
    out = torch.arange(2 * 2 * 16, dtype=torch.float32).view(1, 1, 64)  # order (h, w, t, c)
    video = model.unpatchify(out, 1, 2, 2)                        # (1, 16, 1, 2, 2)
    for c in (0, 5):
        for i in range(2):
            for j in range(2):
                assert float(video[0, c, 0, i, j]) == (i * 2 + j) * 16 + c


def test_cross_attention_zero_context_equals_none():
    config = dataclasses.replace(TINY, cross_attention=True, context_dim=8)
    model = randomised(JointDiT(config))
    x, c_noise = torch.randn(1, 69, 3, 4, 4), torch.tensor([0.2])
    zeros = torch.zeros(1, 512, 8)
    torch.testing.assert_close(model(x, c_noise), model(x, c_noise, context=zeros))
    assert not torch.allclose(model(x, c_noise), model(x, c_noise, context=torch.randn(1, 5, 8)))
    with pytest.raises(ValueError):
        JointDiT(TINY)(x, c_noise, context=zeros)


def test_bf16_autocast_forward_close_to_fp32():
    model = randomised(JointDiT(TINY))
    x, c_noise = torch.randn(2, 69, 3, 4, 4), torch.tensor([0.1, -0.5])
    full = model(x, c_noise)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        half = model(x, c_noise).float()
    assert torch.isfinite(half).all()
    assert float((half - full).abs().max()) < 0.05 * float(full.abs().max())


def test_state_dict_round_trip_through_safetensors(tmp_path):
    model = randomised(JointDiT(TINY))
    path = tmp_path / "dit.safetensors"
    save_file(model.state_dict(), str(path))
    fresh = JointDiT(TINY)
    fresh.load_state_dict(load_file(str(path)))
    x, c_noise = torch.randn(1, 69, 3, 4, 4), torch.tensor([0.4])
    assert torch.equal(model(x, c_noise), fresh(x, c_noise))


# ---------------------------------------------------------------- sizes and released weights


def test_preset_parameter_counts():
    assert param_count(TINY) < 500_000
    assert 10e6 <= param_count(DIT_PRESETS["small"]) <= 30e6
    assert abs(param_count(DIT_PRESETS["unirelight-7b"]) - 7e9) / 7e9 < 0.05


def released_7b_shapes() -> dict[str, tuple[int, ...]]:
    """Parameter names and shapes of the released GeneralDIT 7B network (FA-CA-MLP, AdaLN-LoRA 256)."""
    d, lora, ctx = 4096, 256, 1024
    shapes = {
        "x_embedder.proj.1.weight": (d, 72 * 2 * 2),
        "view_embeddings.weight": (3, 3),
        "t_embedder.1.linear_1.weight": (d, d),
        "t_embedder.1.linear_2.weight": (3 * d, d),
        "affline_norm.weight": (d,),
        "final_layer.linear.weight": (2 * 2 * 16, d),
        "final_layer.adaLN_modulation.1.weight": (lora, d),
        "final_layer.adaLN_modulation.2.weight": (2 * d, lora),
    }
    for i in range(28):
        for j in range(3):
            prefix = f"blocks.block{i}.blocks.{j}."
            shapes[prefix + "adaLN_modulation.1.weight"] = (lora, d)
            shapes[prefix + "adaLN_modulation.2.weight"] = (3 * d, lora)
        for j, kv in ((0, d), (1, ctx)):
            attn = f"blocks.block{i}.blocks.{j}.block.attn."
            shapes[attn + "to_q.0.weight"] = (d, d)
            shapes[attn + "to_q.1.weight"] = (128,)
            shapes[attn + "to_k.0.weight"] = (d, kv)
            shapes[attn + "to_k.1.weight"] = (128,)
            shapes[attn + "to_v.0.weight"] = (d, kv)
            shapes[attn + "to_out.0.weight"] = (d, d)
        shapes[f"blocks.block{i}.blocks.2.block.layer1.weight"] = (4 * d, d)
        shapes[f"blocks.block{i}.blocks.2.block.layer2.weight"] = (d, 4 * d)
    return shapes


def test_released_7b_names_map_onto_ours_with_matching_shapes():
    with torch.device("meta"):
        ours = dict(JointDiT(DIT_PRESETS["unirelight-7b"]).named_parameters())
    released = released_7b_shapes()
    mapped = {}
    for name, shape in released.items():
        target = released_to_ours(name)
        assert target in ours, (name, target)
        assert tuple(ours[target].shape) == shape, name
        mapped[target] = name
    assert set(mapped) == set(ours)                               # one-to-one, nothing left over
    assert sum(torch.Size(s).numel() for s in released.values()) == param_count(DIT_PRESETS["unirelight-7b"])


def test_convert_released_state_dict_strips_prefix_and_reports_leftovers():
    state = {"net.view_embeddings.weight": torch.ones(3, 3), "net.pos_embedder.seq": torch.arange(4.0),
             "net.blocks.block0.blocks.0.block.attn.to_q.1._extra_state": torch.zeros(1),
             "logvar.0.weight": torch.zeros(1)}
    converted, unmapped = convert_released_state_dict(state)
    assert list(converted) == ["clip_type_embed.weight"]
    assert sorted(unmapped) == sorted(set(state) - {"net.view_embeddings.weight"})


def test_small_config_survives_json_style_round_trip():
    config = DIT_PRESETS["small"]
    data = dataclasses.asdict(config)
    data["rope_extrapolation"] = list(data["rope_extrapolation"])
    rebuilt = DiTConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})
    assert rebuilt == config


def test_bf16_weights_accept_fp32_inputs():
    model = randomised(JointDiT(TINY)).to(torch.bfloat16)
    out = model(torch.randn(1, 69, 3, 4, 4), torch.tensor([0.3]))
    assert out.dtype == torch.bfloat16 and torch.isfinite(out.float()).all()


def test_forward_rejects_frames_that_are_not_three_clips():
    with pytest.raises(ValueError):
        JointDiT(TINY)(torch.randn(1, 69, 4, 4, 4), torch.tensor([0.3]))
