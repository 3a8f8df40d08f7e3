"""Our JointDiT against diffusers' `CosmosTransformer3DModel`, an independent Cosmos-Predict1 DiT.

The same random weights (renamed by `diffusers_name_map`) and the same inputs go through both; each
building block and the whole network must agree. Where diffusers departs from the released
UniRelight network the test says so by name and compares what should agree; docs/INTERFACES.md
("Cross-check against diffusers") records each difference and which side the released code takes.
"""

import ast
import math
import re
from pathlib import Path

import pytest
import torch
from diffusers.models.transformers.transformer_cosmos import CosmosTransformer3DModel
from torch import nn

from relight_core.dit import (
    CHANNELS, NUM_CLIPS, TOKEN_CHANNELS, DiTConfig, JointDiT, modulated_layer_norm,
)
from relight_core.released import released_to_ours
from relight_core.rope import rope_angles
from tests.factory import released_names

# The released block structure in miniature (FA-CA-MLP, AdaLN-LoRA, t-RoPE NTK ratio 2), context on.
MINI = DiTConfig(width=64, depth=2, num_heads=2, adaln_lora_dim=16, cross_attention=True, context_dim=32)
T, H, W = 2, 8, 8                       # latent frames of one clip, latent height, width
ATOL = 2e-5                             # fp32; the blocks differ by ≤ 1e-6, the whole network by ≤ 5e-6


@pytest.fixture(autouse=True)
def no_grad():
    with torch.no_grad():
        yield


# ------------------------------------------------------------------ the name map


def diffusers_name_map() -> list[tuple[str, str]]:
    """(our name regex, diffusers name template), `\\1` = block index; like `released_key_map`."""
    table = [
        (r"patch_embed\.weight", "patch_embed.proj.weight"),
        (r"t_embedder\.linear_([12])\.weight", r"time_embed.t_embedder.linear_\1.weight"),
        (r"t_embedder\.norm\.weight", "time_embed.norm.weight"),
        (r"final_layer\.modulation\.down\.weight", "norm_out.linear_1.weight"),
        (r"final_layer\.modulation\.up\.weight", "norm_out.linear_2.weight"),
        (r"final_layer\.linear\.weight", "proj_out.weight"),
        (r"blocks\.(\d+)\.mlp\.fc1\.weight", r"transformer_blocks.\1.ff.net.0.proj.weight"),
        (r"blocks\.(\d+)\.mlp\.fc2\.weight", r"transformer_blocks.\1.ff.net.2.weight"),
    ]
    for ours, norm in (("self_attn", "norm1"), ("cross_attn", "norm2"), ("mlp", "norm3")):
        table.append((rf"blocks\.(\d+)\.{ours}_mod\.down\.weight", rf"transformer_blocks.\1.{norm}.linear_1.weight"))
        table.append((rf"blocks\.(\d+)\.{ours}_mod\.up\.weight", rf"transformer_blocks.\1.{norm}.linear_2.weight"))
    parts = {"q_proj": "to_q", "k_proj": "to_k", "v_proj": "to_v", "out_proj": "to_out.0",
             "q_norm": "norm_q", "k_norm": "norm_k"}
    for ours, attn in (("self_attn", "attn1"), ("cross_attn", "attn2")):
        for part, theirs in parts.items():
            table.append((rf"blocks\.(\d+)\.{ours}\.{part}\.weight", rf"transformer_blocks.\1.{attn}.{theirs}.weight"))
    return table


def ours_to_diffusers(name: str) -> str | None:
    """The diffusers name of one of our parameters; None for the UniRelight-only clip-type embedding."""
    for pattern, target in diffusers_name_map():
        match = re.fullmatch(pattern, name)
        if match is not None:
            return match.expand(target)
    return None


def released_to_diffusers(name: str) -> str:
    """diffusers' own Cosmos-1.0 conversion (scripts/convert_cosmos_to_diffusers.py), restated: ordered
    substring renames, then `blocks.blockN` → `transformer_blocks.N`. An independent released → diffusers map."""
    renames = [("t_embedder.1", "time_embed.t_embedder"), ("affline_norm", "time_embed.norm"),
               (".blocks.0.block.attn", ".attn1"), (".blocks.1.block.attn", ".attn2"), (".blocks.2.block", ".ff")]
    renames += [(f".blocks.{i}.adaLN_modulation.{k}", f".norm{i + 1}.linear_{k}") for i in range(3) for k in (1, 2)]
    renames += [("to_q.0", "to_q"), ("to_q.1", "norm_q"), ("to_k.0", "to_k"), ("to_k.1", "norm_k"),
                ("to_v.0", "to_v"), ("layer1", "net.0.proj"), ("layer2", "net.2"), ("proj.1", "proj"),
                ("x_embedder", "patch_embed"), ("final_layer.adaLN_modulation.1", "norm_out.linear_1"),
                ("final_layer.adaLN_modulation.2", "norm_out.linear_2"), ("final_layer.linear", "proj_out")]
    for old, new in renames:
        name = name.replace(old, new)
    return re.sub(r"^blocks\.block(\d+)\.", r"transformer_blocks.\1.", name)


# ------------------------------------------------------------------ the two models


def build_diffusers(config: DiTConfig) -> CosmosTransformer3DModel:
    ratio_h, ratio_w, ratio_t = config.rope_extrapolation
    return CosmosTransformer3DModel(
        in_channels=TOKEN_CHANNELS,         # our 72 token channels, padding mask and clip type included
        out_channels=config.out_channels,
        num_attention_heads=config.num_heads,
        attention_head_dim=config.head_dim,
        num_layers=config.depth,
        mlp_ratio=config.mlp_ratio,
        text_embed_dim=config.context_dim,
        adaln_lora_dim=config.adaln_lora_dim,
        patch_size=(config.patch_temporal, config.patch_spatial, config.patch_spatial),
        rope_scale=(ratio_t, ratio_h, ratio_w),  # diffusers orders (t, h, w)
        concat_padding_mask=False,          # the padding mask is already one of the 72 channels
        # Difference 1: diffusers' default (Cosmos-1.0 7B base models) adds a learnable absolute position
        # embedding in every block; the UniRelight net (training `faditv2_7b`, legacy_patch_emb=False,
        # no extra_per_block_abs_pos_emb) has none, and neither do we.
        extra_pos_embed_type=None,
    ).eval()


@pytest.fixture(scope="module")
def models():
    """(ours, theirs) with identical random weights; diffusers' QK-norm eps set to the released 1e-6."""
    generator = torch.Generator().manual_seed(0)
    ours = JointDiT(MINI).eval()
    with torch.no_grad():
        for p in ours.parameters():          # every weight random, so zero-initialised paths count too
            p.copy_(torch.randn(p.shape, generator=generator) * 0.2)
    theirs = build_diffusers(MINI)
    mapped = {ours_to_diffusers(n): v for n, v in ours.state_dict().items() if ours_to_diffusers(n)}
    theirs.load_state_dict(mapped, strict=True)
    for block in theirs.transformer_blocks:
        for attn in (block.attn1, block.attn2):
            for norm in (attn.norm_q, attn.norm_k):
                # Difference 2: diffusers' `Attention(qk_norm="rms_norm")` keeps its default eps 1e-5; the
                # released code builds these RMSNorms with eps 1e-6 (`get_normalization("R")`), as we do.
                assert norm.eps == 1e-5
                norm.eps = 1e-6
    assert ours.blocks[0].self_attn.q_norm.eps == ours.blocks[0].cross_attn.k_norm.eps == 1e-6
    return ours, theirs


def max_diff(a: torch.Tensor, b: torch.Tensor) -> float:
    assert a.shape == b.shape, (a.shape, b.shape)
    return (a.float() - b.float()).abs().max().item()


def one_clip_rope(config: DiTConfig, t: int, h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Our cos, sin half-angle tables [t·h·w, hd/2] for a single clip (no per-clip repeat)."""
    angles = rope_angles(config.head_dim, t, h, w, config.rope_extrapolation, config.rope_theta)
    half = angles[:, :config.head_dim // 2]
    return half.cos(), half.sin()


def test_name_map_covers_every_weight_and_agrees_with_the_released_map(models):
    ours, theirs = models
    names = {n: ours_to_diffusers(n) for n in ours.state_dict()}
    assert [n for n, d in names.items() if d is None] == ["clip_type_embed.weight"]   # UniRelight only
    assert sorted(d for d in names.values() if d) == sorted(theirs.state_dict())      # one to one
    # Composing our released → ours map with ours → diffusers gives diffusers' own released → diffusers map.
    for released in released_names(MINI.depth):
        if released != "view_embeddings.weight":
            assert ours_to_diffusers(released_to_ours(released)) == released_to_diffusers(released), released


def test_diffusers_is_a_test_dependency_only():
    root = Path(__file__).resolve().parents[1]
    for path in [*root.glob("relight_core/**/*.py"), *root.glob("ui/**/*.py"), root / "app.py"]:
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            assert not any(n.split(".")[0] == "diffusers" for n in names), path


def test_patch_embedding(models):
    ours, theirs = models
    x = torch.randn(2, TOKEN_CHANNELS, T, H, W)
    ref = theirs.patch_embed(x).flatten(1, 3)                                         # (B, L, D)
    assert max_diff(ours.patch_embed(ours.patchify(x)), ref) < ATOL


@pytest.mark.parametrize("batch", [1, 2])                # one sample takes the fused LayerNorm path
def test_timestep_embedding_and_adaln_lora_modulation(models, batch):
    ours, theirs = models
    c_noise = torch.tensor([0.25 * math.log(3.0), 0.25 * math.log(0.02)])[:batch]       # c_noise of σ 3, 0.02
    x = torch.randn(batch, 40, MINI.width)
    emb, lora = ours.t_embedder(c_noise)                                              # (B, D), (B, 3D)
    temb, embedded = theirs.time_embed(x, c_noise)
    assert max_diff(emb, embedded) < ATOL and max_diff(lora, temb) < ATOL
    for ours_block, their_block in zip(ours.blocks, theirs.transformer_blocks):
        pairs = ((ours_block.self_attn_mod, their_block.norm1), (ours_block.cross_attn_mod, their_block.norm2),
                 (ours_block.mlp_mod, their_block.norm3))
        for mod, norm in pairs:
            shift, scale, gate = mod(emb, lora)
            normed, their_gate = norm(x, embedded, temb)
            assert max_diff(modulated_layer_norm(x, shift, scale), normed) < ATOL
            assert max_diff(gate[:, None], their_gate) < ATOL
    shift, scale = ours.final_layer.modulation(emb, lora)
    assert max_diff(modulated_layer_norm(x, shift, scale), theirs.norm_out(x, embedded, temb)) < ATOL


@pytest.mark.parametrize("fps", [None, 24])              # the released inference passes fps = 24
def test_rope_tables(models, fps):
    _, theirs = models
    cos, sin = theirs.rope(torch.zeros(1, TOKEN_CHANNELS, T, 2 * H, 2 * W), fps=fps)   # (L, hd), [t|h|w] twice
    ours_cos, ours_sin = one_clip_rope(MINI, T, H, W)                                  # (L, hd/2)
    assert max_diff(torch.cat([ours_cos, ours_cos], -1), cos) < ATOL
    assert max_diff(torch.cat([ours_sin, ours_sin], -1), sin) < ATOL


def test_self_attention_with_qk_rmsnorm_and_rope(models):
    ours, theirs = models
    x = torch.randn(2, T * H * W // 4, MINI.width)
    rope = one_clip_rope(MINI, T, H // 2, W // 2)
    their_rope = theirs.rope(torch.zeros(1, TOKEN_CHANNELS, T, H, W))
    for ours_block, their_block in zip(ours.blocks, theirs.transformer_blocks):
        out = ours_block.self_attn(x, rope=rope)
        assert max_diff(out, their_block.attn1(x, image_rotary_emb=their_rope)) < ATOL


def test_cross_attention_and_its_zero_context(models):
    ours, theirs = models
    x = torch.randn(2, 24, MINI.width)
    context = torch.randn(2, 7, MINI.context_dim)
    for ours_block, their_block in zip(ours.blocks, theirs.transformer_blocks):
        out = ours_block.cross_attn(x, context)
        assert max_diff(out, their_block.attn2(x, encoder_hidden_states=context)) < ATOL
        # The released context is all zeros: both give exactly 0, which is why we skip the sub-layer.
        zero = their_block.attn2(x, encoder_hidden_states=torch.zeros_like(context))
        assert torch.equal(zero, torch.zeros_like(zero))


def test_mlp(models):
    ours, theirs = models
    x = torch.randn(2, 24, MINI.width)
    for ours_block, their_block in zip(ours.blocks, theirs.transformer_blocks):
        assert max_diff(ours_block.mlp(x), their_block.ff(x)) < ATOL


def test_final_layer_and_unpatchify(models):
    ours, theirs = models
    c_noise = torch.tensor([0.3, -1.2])
    tokens = torch.randn(2, T * (H // 2) * (W // 2), MINI.width)
    emb, lora = ours.t_embedder(c_noise)
    temb, embedded = theirs.time_embed(tokens, c_noise)
    out = ours.final_layer(tokens, emb, lora)
    ref = theirs.proj_out(theirs.norm_out(tokens, embedded, temb))
    assert max_diff(out, ref) < ATOL
    # diffusers' unpatchify, as in its forward: features ordered (h, w, t, c), like the release.
    p = MINI.patch_spatial
    video = ref.unflatten(2, (p, p, MINI.patch_temporal, -1)).unflatten(1, (T, H // 2, W // 2)).permute(0, 7, 1, 6, 2, 4, 3, 5)
    assert max_diff(ours.unpatchify(ref, T, H, W), video.flatten(6, 7).flatten(4, 5).flatten(2, 3)) == 0


class RopePerClip(nn.Module):
    """diffusers' RoPE for the first of the three clips, repeated for each (the released layout)."""

    def __init__(self, rope: nn.Module):
        super().__init__()
        self.rope = rope

    def forward(self, hidden_states: torch.Tensor, fps=None) -> tuple[torch.Tensor, torch.Tensor]:
        cos, sin = self.rope(hidden_states[:, :, :hidden_states.shape[2] // NUM_CLIPS], fps=fps)
        return cos.repeat(NUM_CLIPS, 1), sin.repeat(NUM_CLIPS, 1)


@pytest.mark.parametrize("with_context", [False, True])
def test_whole_network_on_one_clip_with_the_joint_parts_neutral(models, with_context):
    """Three identical clips with a zero clip-type embedding are one clip: attention over three copies
    of every key (at the same repeated RoPE positions) is attention over one. Each of our three output
    clips must equal diffusers' output on that single clip."""
    ours, theirs = models
    generator = torch.Generator().manual_seed(1)
    clip = torch.randn(2, CHANNELS["padding_mask"].stop, T, H, W, generator=generator)     # (B, 69, t, h, w)
    c_noise = torch.tensor([0.8, -0.4])
    context = torch.randn(2, 5, MINI.context_dim, generator=generator)
    saved = ours.clip_type_embed.weight.clone()
    ours.clip_type_embed.weight.zero_()
    try:
        out = ours(clip.repeat(1, 1, NUM_CLIPS, 1, 1), c_noise, context if with_context else None)
    finally:
        ours.clip_type_embed.weight.copy_(saved)
    x72 = torch.cat([clip, torch.zeros(2, 3, T, H, W)], dim=1)                             # zero clip-type channels
    # The released model's text context is zeros; ours skips cross-attention for it (context=None).
    ref = theirs(x72, c_noise, context if with_context else torch.zeros_like(context), return_dict=False)[0]
    for k in range(NUM_CLIPS):
        assert max_diff(out[:, :, k * T:(k + 1) * T], ref) < 1e-4


def test_whole_network_on_three_clips_with_diffusers_rope_repeated_per_clip(models):
    """Distinct clips and the learned clip-type channels: diffusers agrees once its RoPE is computed for
    one clip and repeated for each (the released `MultiviewVideoRopePosition3DEmb`), and only then."""
    ours, theirs = models
    generator = torch.Generator().manual_seed(2)
    x = torch.randn(1, CHANNELS["padding_mask"].stop, NUM_CLIPS * T, H, W, generator=generator)
    c_noise = torch.tensor([0.1])
    context = torch.zeros(1, 5, MINI.context_dim)
    out = ours(x, c_noise)
    x72 = ours.embed_inputs(x)                                                            # (1, 72, 3t, h, w)
    contiguous = theirs(x72, c_noise, context, return_dict=False)[0]
    # Difference 3 (UniRelight-specific): diffusers numbers frames 0 … 3t−1 across the joint sequence.
    assert max_diff(out, contiguous) > 1e-3                 # measured 0.019 against 4e-6 below
    rope = theirs.rope
    theirs.rope = RopePerClip(rope)
    try:
        ref = theirs(x72, c_noise, context, return_dict=False)[0]
    finally:
        theirs.rope = rope
    assert max_diff(out, ref) < 1e-4
