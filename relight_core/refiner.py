"""The default model's detail refiner: a small convolutional U-Net run after the DiT.

The default model's pixel tokenizer gives the DiT 8×8-pixel tokens; what it predicts inside a token
comes out of one linear layer, so edges — shadow borders, texture the albedo should keep, the
shading the albedo should lose — come out soft. The refiner looks at the full-resolution input next
to the DiT's relit and albedo frames (all at the model's size) and adds a correction:

    relit', albedo' = base_relit + Δ_relit, base_albedo + Δ_albedo,
    (Δ_relit, Δ_albedo) = U-Net(input, relit, albedo[, base_relit, base_albedo])

where the base is the DiT's frames ("raw") or those after the model's offset filter ("filtered":
`ModelSpec.offset_filter`, the hand-tuned form of the same idea), and only the `clips` it is
configured for are corrected. A refiner with `lighting` also sees the target light: the camera-frame
probe area-averaged to 8×8 (`light_features`), through an MLP that scales and shifts every channel of
its middle and decoder levels (FiLM; zero at the start, so it begins as the refiner without light);
with `light_detail` k the MLP also sees a k×k grid of the probe (where a sun is, to ~11° at 16×16),
and with `film_encoder` the encoder levels are modulated too, so the light can steer what the network
works out of the frames and not only how it combines it. With `transport` k (and a relit gain) the relit log
gain also gets the log of a shading that is *linear in the light*, as light transport is: each pixel of the
1/4-size decoder level (a shallower one in a refiner of fewer levels) weights the probe's k×k cells (a softmax of
a 1×1 layer's logits; which directions light that pixel, and how much) and its shading is that weighted mean of
the probe, each channel over its mean over the cells. Its weights start uniform, a shading of 1: the refiner it
starts from, unchanged. With `reshade` the term is instead gate·(log transport shading − log own shading), the
own shading the base's relit ÷ albedo averaged to that level, the gate a 1×1 layer's (zero at the start): where
the gate is 1 the base's shading is swapped for the transport one. A refiner
without lighting follows the probe only through the DiT. With `relit_gain` the relit correction is not
added but multiplies the relit base as a smooth gain (one log gain per k×k-pixel cell, interpolated):
it can brighten, darken and tint regions, and cannot draw an edge the base does not have or lift its
blacks much — an added correction did both on a photo unlike the training scenes (docs/QUALITY.md).
With `input_mix` as well, the gained relit frame is mixed, cell by cell and as smoothly, with the input
under a gain of its own: where the light changes little, or only by a smooth ratio, the input's own
detail (texture, outlines) can come through instead of the DiT's softer frame.
Its last layer starts at zero, so an untrained refiner returns its base unchanged. With `flip_average`
its correction is the mean of the one for the frames and the one for their mirror image flipped back
(two passes, one batch; the mirrored pass sees the mirrored light, u → 1 − u). With `colour_average` it is
the mean over the six orders of the colour channels — the frames' and the light's reordered alike, each
correction's put back — as the training's colour permutation (`refine --permute-colours`) says a scene with
its colours swapped is as plausible a one (six times the passes). With `grid_shift` s it is the mean of the
one for the frames and the one for the frames padded by s pixels on every side (reflected) and cropped back:
the U-Net halves the frame at each level, so what its coarse levels get wrong is tied to their grid (16-pixel
cells with five levels), and that grid falls elsewhere on the scene in the second pass (twice the passes).

A model folder holds up to two: `refiner.safetensors` (config.json's "refiner" entry) and
`relit_refiner.safetensors` ("relit_refiner"), each correcting its clips from the same frames. The
shipped default has both: the first for its albedo alone, the second for the relit frames, seeing the
light and correcting them by a smooth gain (docs/QUALITY.md). Trained by `python -m relight_core.training.refine` on the
frozen DiT's outputs.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import torch
from torch import nn
from torch.nn import functional as F

REFINER_FILE = "refiner.safetensors"
RELIT_REFINER_FILE = "relit_refiner.safetensors"
REFINER_SLOTS = {"refiner": REFINER_FILE, "relit_refiner": RELIT_REFINER_FILE}   # config.json key → weights
LIGHT_GRID = 8                                 # the probe as the refiner sees it: 8×8 area averages
LIGHT_FEATURES = 3 * LIGHT_GRID * LIGHT_GRID
GAIN_EPSILON = 0.02                            # `relit_gain`: black plus this is what the gain multiplies
MIX_OFFSET = 5.0                               # `input_mix`: the input's weight is sigmoid(MIX_SCALE·z − MIX_OFFSET):
MIX_SCALE = 8.0                                # ~0.007 at z = 0, and the logit learns as fast as a gain would
CONFIG_KEYS = ('"widths" (1 to 6 whole numbers from 1 to 1024), "blocks" (0 to 8), "base" ("raw" or "filtered"), '
               '"clips" (["relit", "albedo"] or one of them), "flip_average" and "lighting" (true or false), '
               '"relit_gain" (a cell of 0 to 64 pixels), "input_mix" (true or false; true only with a relit_gain '
               'cell and the relit clip), "light_detail" (0, or a grid of 2 to 32 with "lighting" true), '
               '"film_encoder" (true or false; true only with "lighting" true), "transport" (0, or a grid of 2 to 32 '
               'with "lighting" true, a relit_gain cell and the relit clip), "reshade" (true or false; true only with '
               '"transport"), "colour_average" (true or false), "grid_shift" (0 to 64 pixels) and "strength" (0 to 2)')
TRANSPORT_LAYERS = ("transport_head.", "transport_gate.")   # `transport`'s weights (new to a refiner without it)
TRANSPORT_FLOOR = 1e-3                         # `transport`: its shading is floored here before the log


@dataclass(frozen=True)
class RefinerConfig:
    widths: tuple[int, ...] = (24, 48, 96, 128)   # channels at full, 1/2, 1/4, 1/8 resolution
    blocks: int = 1                               # residual blocks per level (twice at the bottom)
    base: str = "raw"                             # what the corrections add to: the DiT's frames ("raw") or
                                                  # those after the model's offset filter ("filtered")
    clips: tuple[str, ...] = ("relit", "albedo")  # the frames it corrects; the others stay the base's
    flip_average: bool = False                    # average the correction with the mirror image's
    lighting: bool = False                        # sees the target light (FiLM from `light_features`)
    light_detail: int = 0                         # with lighting: k > 0 also feeds the FiLM a k×k grid of
                                                  # the probe (`Refiner.light`), beside the 8×8 one
    film_encoder: bool = False                    # with lighting: FiLM on the encoder levels as well
    transport: int = 0                            # with lighting and relit_gain: k > 0 adds to the relit log gain
                                                  # the log of a shading *linear in the light*: per pixel, a
                                                  # weighted mean of the probe's k×k cells (`Refiner.forward`)
    reshade: bool = False                         # with transport: the term is gated, per pixel, and replaces the
                                                  # base's own shading (relit ÷ albedo) by the transport one
    relit_gain: int = 0                           # 0: the relit correction is added; k > 0: it is a log gain
                                                  # on the relit base, averaged over k×k-pixel cells and
                                                  # smoothly interpolated (`corrected`): it can brighten,
                                                  # darken and tint, but draws no edge the base lacks
    input_mix: bool = False                       # with relit_gain: the relit frame is a smooth per-cell mix of
                                                  # the gained base and the input under a gain of its own
                                                  # (`corrected`): the input's detail where it holds
    colour_average: bool = False                  # average the correction over the six orders of the colour
                                                  # channels (of the frames and the light alike), put back
    grid_shift: int = 0                           # s > 0: average the correction with the one for the frames
                                                  # padded by s px (reflected), cropped back (`correction`)
    strength: float = 1.0                         # scales its corrections (the log gain with relit_gain):
                                                  # chosen on held-out scenes by `training.calibrate
                                                  # --strengths`, where a correction learnt on training
                                                  # scenes can overshoot; training always uses 1

    @classmethod
    def from_dict(cls, data: dict) -> "RefinerConfig":
        """The config of a config.json entry (`to_dict`'s form), or ValueError naming what it takes (`CONFIG_KEYS`)."""
        if not isinstance(data, dict):
            raise ValueError(f"a refiner is a JSON object of {CONFIG_KEYS}; got {data!r}")
        widths, blocks = data.get("widths", list(cls.widths)), data.get("blocks", cls.blocks)
        base, clips = data.get("base", cls.base), data.get("clips", list(cls.clips))
        flip_average = data.get("flip_average", cls.flip_average)
        lighting = data.get("lighting", cls.lighting)
        relit_gain = data.get("relit_gain", cls.relit_gain)
        strength = data.get("strength", cls.strength)
        input_mix = data.get("input_mix", cls.input_mix)
        light_detail = data.get("light_detail", cls.light_detail)
        film_encoder = data.get("film_encoder", cls.film_encoder)
        transport = data.get("transport", cls.transport)
        reshade = data.get("reshade", cls.reshade)
        colour_average = data.get("colour_average", cls.colour_average)
        grid_shift = data.get("grid_shift", cls.grid_shift)

        def whole(v, low, high):
            return isinstance(v, int) and not isinstance(v, bool) and low <= v <= high

        if (not isinstance(widths, (list, tuple)) or not 1 <= len(widths) <= 6
                or not all(whole(w, 1, 1024) for w in widths) or not whole(blocks, 0, 8)
                or base not in ("raw", "filtered") or not isinstance(clips, (list, tuple))
                or not clips or not set(clips) <= {"relit", "albedo"} or not isinstance(flip_average, bool)
                or not isinstance(lighting, bool) or not whole(relit_gain, 0, 64)
                or isinstance(strength, bool) or not isinstance(strength, (int, float))
                or not 0 <= strength <= 2 or not isinstance(input_mix, bool)
                or (input_mix and not (relit_gain and "relit" in clips))
                or not whole(light_detail, 0, 32) or 0 < light_detail < 2 or not isinstance(film_encoder, bool)
                or ((light_detail or film_encoder) and lighting is not True)
                or not whole(transport, 0, 32) or 0 < transport < 2
                or (transport and not (lighting is True and relit_gain and "relit" in clips))
                or not isinstance(reshade, bool) or (reshade and not transport) or not isinstance(colour_average, bool)
                or not whole(grid_shift, 0, 64)):
            raise ValueError(f"a refiner takes {CONFIG_KEYS}; got {data!r}")
        return cls(widths=tuple(widths), blocks=blocks, base=base,
                   clips=tuple(c for c in ("relit", "albedo") if c in clips), flip_average=flip_average,
                   lighting=lighting, relit_gain=relit_gain, input_mix=input_mix, strength=float(strength),
                   light_detail=light_detail, film_encoder=film_encoder, transport=transport,
                   reshade=reshade, colour_average=colour_average, grid_shift=grid_shift)

    def to_dict(self) -> dict:
        out = {"widths": list(self.widths), "blocks": self.blocks, "base": self.base, "clips": list(self.clips)}
        if self.flip_average:
            out["flip_average"] = True
        if self.lighting:
            out["lighting"] = True
        if self.relit_gain:
            out["relit_gain"] = self.relit_gain
        if self.input_mix:
            out["input_mix"] = True
        if self.light_detail:
            out["light_detail"] = self.light_detail
        if self.film_encoder:
            out["film_encoder"] = True
        if self.transport:
            out["transport"] = self.transport
        if self.reshade:
            out["reshade"] = True
        if self.colour_average:
            out["colour_average"] = True
        if self.grid_shift:
            out["grid_shift"] = self.grid_shift
        if self.strength != 1.0:
            out["strength"] = self.strength
        return out

    @property
    def shape(self) -> tuple:
        """What its weights depend on (widths, blocks, base, lighting, input_mix: its head's channels,
        light_detail and film_encoder: its FiLM's, transport and reshade: its transport layers); `clips`,
        `flip_average`, `colour_average`, `grid_shift`, `relit_gain` and `strength` only change how they are used, so a run
        may resume or start from weights with other ones."""
        return (self.widths, self.blocks, self.base, self.lighting, self.input_mix, self.light_detail,
                self.film_encoder, self.transport, self.reshade)

    @property
    def light_features(self) -> int:
        """The length of the FiLM's input (`Refiner.light`): the 8×8 grid's and the `light_detail` grid's."""
        return LIGHT_FEATURES + 3 * self.light_detail ** 2 if self.lighting else 0

    @property
    def out_channels(self) -> int:
        """The head's: the relit and albedo corrections, and with `input_mix` the input's log gain and
        the mix's logit."""
        return 10 if self.input_mix else 6

    @property
    def in_channels(self) -> int:
        return 9 if self.base == "raw" else 15


def network_input(base: str, inputs: torch.Tensor, relit: torch.Tensor, albedo: torch.Tensor,
                  filtered: tuple[torch.Tensor, torch.Tensor] | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The refiner's network input [B,9|15,H,W] (the input, the DiT's relit and albedo frames and, for
    base "filtered", those frames after the offset filter; all [B,3,H,W] in [-1, 1]) and the relit and
    albedo frames its corrections add to. The one place the channel order is set, for training and use."""
    parts = [inputs, relit, albedo]
    if base == "filtered":
        if filtered is None:
            raise ValueError("this refiner adds to the filtered frames; pass them")
        parts += list(filtered)
        relit, albedo = filtered
    return torch.cat(parts, dim=1), relit, albedo


def _cell_means(panoramas: torch.Tensor, cells: int) -> torch.Tensor:
    """[B,3,cells,cells] area averages of camera-frame panoramas [B,h,w,3], or ValueError for another shape."""
    if panoramas.dim() != 4 or panoramas.shape[-1] != 3:
        raise ValueError(f"the refiner's light takes panoramas [B,h,w,3]; got {tuple(panoramas.shape)}")
    return F.adaptive_avg_pool2d(panoramas.permute(0, 3, 1, 2).float(), cells)


def transport_light(panoramas: torch.Tensor, cells: int) -> torch.Tensor:
    """[B,3,cells²] the probe for `transport`: camera-frame panoramas [B,h,w,3] area-averaged on a cells×cells
    grid, each channel divided by its mean over the cells (so a uniform weighting of them gives 1: the
    colour of the whole light is the protocol's scale fit's, what varies from place to place is shading)."""
    grid = _cell_means(panoramas, cells).clamp_min(0).flatten(2)
    return grid / grid.mean(2, keepdim=True).clamp_min(1e-6)


def light_features(panoramas: torch.Tensor, cells: int = LIGHT_GRID) -> torch.Tensor:
    """[B,3*cells*cells] lighting features of camera-frame panoramas [B,h,w,3] (linear radiance, any size;
    the packs' 32² lighting grid or a frame-sized panorama alike): area averages on a cells×cells grid
    (8×8 by default), divided by their mean (the protocol fits each channel's scale, so only the light's
    shape and colour count), then log(· + 0.05)."""
    grid = _cell_means(panoramas, cells)
    grid = grid / grid.mean((1, 2, 3), keepdim=True).clamp_min(1e-6)
    return torch.log(grid.clamp_min(0) + 0.05).flatten(1)


def _reordered(images: torch.Tensor, order) -> torch.Tensor:
    """`images` [B,C,H,W] with the channels of every whole RGB triple reordered (new channel j of a triple is
    its old channel order[j]); a channel past the last triple (the input mix's logit) stays."""
    triples = images.shape[1] // 3
    index = [3 * t + o for t in range(triples) for o in order] + list(range(3 * triples, images.shape[1]))
    return images[:, index]


def _inverse(order) -> list[int]:
    return sorted(range(len(order)), key=lambda j: order[j])


class _Block(nn.Module):
    def __init__(self, width: int):
        super().__init__()
        self.conv1 = nn.Conv2d(width, width, 3, padding=1)
        self.conv2 = nn.Conv2d(width, width, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(F.silu(self.conv1(F.silu(x))))


class Refiner(nn.Module):
    """U-Net: [B,9,H,W] (input, relit, albedo in [-1, 1]; with base "filtered" also the filtered relit
    and albedo: [B,15,H,W]) → [B,6,H,W] corrections (relit, albedo; [B,10,H,W] with `input_mix`)."""

    def __init__(self, config: RefinerConfig = RefinerConfig()):
        super().__init__()
        self.config = config
        w = config.widths
        self.stem = nn.Conv2d(config.in_channels, w[0], 3, padding=1)
        self.down = nn.ModuleList(nn.Conv2d(a, b, 3, stride=2, padding=1) for a, b in zip(w[:-1], w[1:]))
        self.enc = nn.ModuleList(nn.Sequential(*[_Block(c) for _ in range(config.blocks)]) for c in w[:-1])
        self.mid = nn.Sequential(*[_Block(w[-1]) for _ in range(2 * config.blocks)])
        self.up = nn.ModuleList(nn.Conv2d(b + a, a, 1) for a, b in zip(w[:-1], w[1:]))
        self.dec = nn.ModuleList(nn.Sequential(*[_Block(c) for _ in range(config.blocks)]) for c in w[:-1])
        self.head = nn.Conv2d(w[0], config.out_channels, 3, padding=1)
        if config.transport:
            # per pixel of the 1/4-size decoder level, logits of a distribution over the probe's cells: zero, so
            # uniform, so a shading of exactly 1 at the start (the same output as without it)
            self.transport_level = min(2, len(w) - 2)
            self.transport_head = nn.Conv2d(w[self.transport_level], config.transport ** 2, 1)
            nn.init.zeros_(self.transport_head.weight)
            nn.init.zeros_(self.transport_head.bias)
        if config.reshade:
            self.transport_gate = nn.Conv2d(w[self.transport_level], 1, 1)     # zero: no change at the start
            nn.init.zeros_(self.transport_gate.weight)
            nn.init.zeros_(self.transport_gate.bias)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        # FiLM: a scale and shift per channel of the middle and of each decoder level, deepest first, then
        # (film_encoder) of each encoder level, shallowest first — after the others, so that the FiLM of a
        # refiner without them is the first part of this one's (`training.refine.initial_weights`)
        self.film_sizes = [w[-1], *reversed(w[:-1])] if config.lighting else []
        if config.film_encoder:
            self.film_sizes += list(w[:-1])
        if config.lighting:
            self.film = nn.Sequential(nn.Linear(config.light_features, 256), nn.SiLU(),
                                      nn.Linear(256, 2 * sum(self.film_sizes)))
            nn.init.zeros_(self.film[-1].weight)
            nn.init.zeros_(self.film[-1].bias)

    def light(self, panoramas: torch.Tensor) -> torch.Tensor:
        """The FiLM's input [B,config.light_features] for camera-frame panoramas [B,h,w,3]: `light_features`
        on the 8×8 grid and, with `light_detail` k, on the k×k grid after it; with `transport` k the probe's
        cells for it follow (`transport_light`, flattened: [B,3k²] more)."""
        features = light_features(panoramas)
        if self.config.light_detail:
            features = torch.cat([features, light_features(panoramas, self.config.light_detail)], dim=1)
        if self.config.transport:
            features = torch.cat([features, transport_light(panoramas, self.config.transport).flatten(1)], dim=1)
        return features

    def forward(self, x: torch.Tensor, light: torch.Tensor | None = None) -> torch.Tensor:
        """Corrections [B,6|10,H,W] for network input `x`; `light` (`light`: [B,config.light_features], and with
        `transport` k the probe's [3,k²] cells after them) for a refiner with lighting (required there, not taken
        otherwise)."""
        if self.config.lighting != (light is not None):
            raise ValueError("a refiner with lighting takes the light's features, one without takes none")
        films, probe = [], None
        if light is not None:
            light = light.to(x.device)
            if self.config.transport:
                light, probe = light[:, :self.config.light_features], light[:, self.config.light_features:]
                probe = probe.float().view(len(x), 3, self.config.transport ** 2)
            params, at = self.film(light).float(), 0
            for size in self.film_sizes:
                films.append((params[:, at:at + size, None, None], params[:, at + size:at + 2 * size, None, None]))
                at += 2 * size

        def modulated(h: torch.Tensor, level: int) -> torch.Tensor:
            if not films:
                return h
            scale, shift = films[level]
            return h * (1 + scale.to(h.dtype)) + shift.to(h.dtype)

        h = self.stem(x)
        skips = []
        encoder_films = 1 + len(self.enc)     # where the encoder's FiLM starts in `films`
        for level, (enc, down) in enumerate(zip(self.enc, self.down)):
            h = enc(h)
            if self.config.film_encoder:
                h = modulated(h, encoder_films + level)
            skips.append(h)
            h = down(F.silu(h))
        h = modulated(self.mid(h), 0)
        for level, i in enumerate(reversed(range(len(skips))), start=1):
            h = F.interpolate(h, size=skips[i].shape[-2:], mode="bilinear", align_corners=False)
            h = modulated(self.dec[i](self.up[i](torch.cat([h, skips[i]], dim=1))), level)
            if probe is not None and i == self.transport_level:
                weights = torch.softmax(self.transport_head(F.silu(h)).float(), dim=1)      # [B,K,h,w]
                shading = torch.einsum("bkyx,bck->bcyx", weights, probe).clamp_min(TRANSPORT_FLOOR)
                log_shading = torch.log(shading)
                if self.config.reshade:
                    # the base's own shading, relit ÷ albedo per channel at this level's size, swapped for the
                    # transport one where the gate says so (the bases: `network_input`'s channels 9–14 or 3–8)
                    at = 9 if self.config.base == "filtered" else 3
                    relit_base, albedo_base = x[:, at:at + 3].float(), x[:, at + 3:at + 6].float()
                    eps = 2 * GAIN_EPSILON
                    own = F.adaptive_avg_pool2d(torch.log((relit_base + 1 + eps) / (albedo_base + 1 + eps)), h.shape[-2:])
                    log_shading = self.transport_gate(F.silu(h)).float() * (log_shading - own)
        out = self.head(F.silu(h))
        if probe is not None:
            # the transport term: log of each pixel's weighted mean of the probe's cells (linear in the light;
            # the weights, from the frames and the light's FiLM, say which directions light that pixel)
            log_shading = F.interpolate(log_shading, size=out.shape[-2:], mode="bilinear", align_corners=False)
            out = torch.cat([out[:, :3] + log_shading.to(out.dtype), out[:, 3:]], dim=1)
        return out

    def correction(self, x: torch.Tensor, panoramas: torch.Tensor | None = None) -> torch.Tensor:
        """The corrections [B,6|10,H,W] for network input `x` [B,9|15,H,W] (`network_input`) and, for a
        refiner with lighting, the target's camera-frame panoramas [B,h,w,3]: the network's own, or with
        `flip_average` the mean of it and the mirror image's (under the mirrored light) flipped back; with
        `grid_shift` each of those the mean of the frames' and the padded frames' cropped back (`_shifted`)."""
        if self.config.lighting and panoramas is None:
            raise ValueError("this refiner sees the light; pass the target's camera-frame panoramas")
        if self.config.colour_average:
            # each order of the colour channels in one batch, each correction's channels put back, averaged
            orders = list(itertools.permutations(range(3)))
            xs = torch.cat([_reordered(x, order) for order in orders])
            lights = torch.cat([panoramas[..., list(order)] for order in orders]) if panoramas is not None else None
            out = self._shifted(xs, lights).split(len(x))
            return sum(_reordered(o, _inverse(order)) for o, order in zip(out, orders)) / len(orders)
        return self._shifted(x, panoramas)

    def _shifted(self, x: torch.Tensor, panoramas: torch.Tensor | None) -> torch.Tensor:
        shift = self.config.grid_shift
        plain = self._mirrored(x, panoramas)
        if not shift:
            return plain
        height, width = x.shape[-2:]
        # reflection needs more pixels than it mirrors; a frame too small for it is padded with its edge
        mode = "reflect" if min(height, width) > shift else "replicate"
        moved = self._mirrored(F.pad(x, (shift,) * 4, mode=mode), panoramas)[..., shift:shift + height, shift:shift + width]
        return (plain + moved) / 2

    def _mirrored(self, x: torch.Tensor, panoramas: torch.Tensor | None) -> torch.Tensor:
        light = self.light(panoramas) if self.config.lighting else None
        if not self.config.flip_average:
            return self.forward(x, light)
        if light is not None:
            light = torch.cat([light, self.light(panoramas.flip(2))])
        both = self.forward(torch.cat([x, x.flip(-1)]), light)
        return (both[:len(x)] + both[len(x):].flip(-1)) / 2

    def refine(self, inputs: torch.Tensor, relit: torch.Tensor, albedo: torch.Tensor,
               filtered: tuple[torch.Tensor, torch.Tensor] | None = None,
               panoramas: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Refined (relit, albedo) [B,3,H,W] in [-1, 1] from the input and the DiT's frames [B,3,H,W]
        in [-1, 1] (and, for base "filtered", those frames after the offset filter; for a refiner with
        lighting, the target's camera-frame panoramas [B,h,w,3]); any frame size (each level's result
        is brought back to its skip's size)."""
        x, relit, albedo = network_input(self.config.base, inputs, relit, albedo, filtered)
        return self.corrected(self.correction(x, panoramas).to(relit.dtype), relit, albedo, inputs=inputs)

    def corrected(self, delta: torch.Tensor, relit: torch.Tensor, albedo: torch.Tensor, clamp: bool = True,
                  inputs: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The base frames (relit, albedo) [B,3,H,W] in [-1, 1] with the corrections `delta` [B,6|10,H,W]
        applied to the clips it corrects (the others come back as they were): added, or with `relit_gain`
        the relit one as a smooth gain, (relit + ε)·exp(g) − ε in [0, 1] display values (ε = 0.02), g the
        correction averaged over relit_gain-pixel cells and bilinearly interpolated back; both scaled by
        `strength` (the gain raised to it). With `input_mix` the relit frame is then mixed, cell by cell,
        with the input frames `inputs` [B,3,H,W] (required there) under a smooth gain of their own:
        (1 − m)·relit′ + m·((input + ε)·exp(g_in) − ε), m = sigmoid(8z − 5) (~0.007 at the start), g_in
        and z made smooth like g. The one place this is done, for training (`clamp` False: the loss sees
        values past [-1, 1]) and for use."""
        def bounded(x: torch.Tensor) -> torch.Tensor:
            return x.clamp(-1, 1) if clamp else x

        if self.config.strength != 1.0:
            delta = delta * self.config.strength

        if "relit" in self.config.clips:
            if self.config.relit_gain:
                cell = self.config.relit_gain
                h, w = relit.shape[-2:]

                def smooth(d: torch.Tensor) -> torch.Tensor:
                    d = F.adaptive_avg_pool2d(d.float(), (-(-h // cell), -(-w // cell)))
                    return F.interpolate(d, size=(h, w), mode="bilinear", align_corners=False)

                eps = 2 * GAIN_EPSILON      # in [-1, 1] units
                gained = (relit.float() + 1 + eps) * torch.exp(smooth(delta[:, :3]).clamp(-4, 4)) - eps - 1
                if self.config.input_mix:
                    if inputs is None:
                        raise ValueError("this refiner mixes the input into the relit frames; pass the input")
                    own = (inputs.float() + 1 + eps) * torch.exp(smooth(delta[:, 6:9]).clamp(-4, 4)) - eps - 1
                    mix = torch.sigmoid(MIX_SCALE * smooth(delta[:, 9:10]) - MIX_OFFSET)
                    gained = gained + mix * (own - gained)
                relit = bounded(gained.to(relit.dtype))
            else:
                relit = bounded(relit + delta[:, :3])
        if "albedo" in self.config.clips:
            albedo = bounded(albedo + delta[:, 3:])
        return relit, albedo

