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
works out of the frames and not only how it combines it.
one without it follows the probe only through the DiT. With `relit_gain` the relit correction is not
added but multiplies the relit base as a smooth gain (one log gain per k×k-pixel cell, interpolated):
it can brighten, darken and tint regions, and cannot draw an edge the base does not have or lift its
blacks much — an added correction did both on a photo unlike the training scenes (docs/QUALITY.md).
With `input_mix` as well, the gained relit frame is mixed, cell by cell and as smoothly, with the input
under a gain of its own: where the light changes little, or only by a smooth ratio, the input's own
detail (texture, outlines) can come through instead of the DiT's softer frame.
Its last layer starts at zero, so an untrained refiner returns its base unchanged. With `flip_average`
its correction is the mean of the one for the frames and the one for their mirror image flipped back
(two passes, one batch; the mirrored pass sees the mirrored light, u → 1 − u).

A model folder holds up to two: `refiner.safetensors` (config.json's "refiner" entry) and
`relit_refiner.safetensors` ("relit_refiner"), each correcting its clips from the same frames. The
shipped default has both: the first for its albedo alone, the second for the relit frames, seeing the
light and correcting them by a smooth gain (docs/QUALITY.md). Trained by `python -m relight_core.training.refine` on the
frozen DiT's outputs.
"""

from __future__ import annotations

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
               '"film_encoder" (true or false; true only with "lighting" true) and "strength" (0 to 2)')


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
    relit_gain: int = 0                           # 0: the relit correction is added; k > 0: it is a log gain
                                                  # on the relit base, averaged over k×k-pixel cells and
                                                  # smoothly interpolated (`corrected`): it can brighten,
                                                  # darken and tint, but draws no edge the base lacks
    input_mix: bool = False                       # with relit_gain: the relit frame is a smooth per-cell mix of
                                                  # the gained base and the input under a gain of its own
                                                  # (`corrected`): the input's detail where it holds
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
                or ((light_detail or film_encoder) and lighting is not True)):
            raise ValueError(f"a refiner takes {CONFIG_KEYS}; got {data!r}")
        return cls(widths=tuple(widths), blocks=blocks, base=base,
                   clips=tuple(c for c in ("relit", "albedo") if c in clips), flip_average=flip_average,
                   lighting=lighting, relit_gain=relit_gain, input_mix=input_mix, strength=float(strength),
                   light_detail=light_detail, film_encoder=film_encoder)

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
        if self.strength != 1.0:
            out["strength"] = self.strength
        return out

    @property
    def shape(self) -> tuple:
        """What its weights depend on (widths, blocks, base, lighting, input_mix: its head's channels,
        light_detail and film_encoder: its FiLM's); `clips`, `flip_average`, `relit_gain` and `strength`
        only change how they are used, so a run may resume or start from weights with other ones."""
        return self.widths, self.blocks, self.base, self.lighting, self.input_mix, self.light_detail, self.film_encoder

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


def light_features(panoramas: torch.Tensor, cells: int = LIGHT_GRID) -> torch.Tensor:
    """[B,3*cells*cells] lighting features of camera-frame panoramas [B,h,w,3] (linear radiance, any size;
    the packs' 32² lighting grid or a frame-sized panorama alike): area averages on a cells×cells grid
    (8×8 by default), divided by their mean (the protocol fits each channel's scale, so only the light's
    shape and colour count), then log(· + 0.05)."""
    if panoramas.dim() != 4 or panoramas.shape[-1] != 3:
        raise ValueError(f"light_features takes panoramas [B,h,w,3]; got {tuple(panoramas.shape)}")
    grid = F.adaptive_avg_pool2d(panoramas.permute(0, 3, 1, 2).float(), cells)
    grid = grid / grid.mean((1, 2, 3), keepdim=True).clamp_min(1e-6)
    return torch.log(grid.clamp_min(0) + 0.05).flatten(1)


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
        on the 8×8 grid and, with `light_detail` k, on the k×k grid after it."""
        features = light_features(panoramas)
        if self.config.light_detail:
            features = torch.cat([features, light_features(panoramas, self.config.light_detail)], dim=1)
        return features

    def forward(self, x: torch.Tensor, light: torch.Tensor | None = None) -> torch.Tensor:
        """Corrections [B,6|10,H,W] for network input `x`; `light` [B,config.light_features] (`light`) for
        a refiner with lighting (required there, not taken otherwise)."""
        if self.config.lighting != (light is not None):
            raise ValueError("a refiner with lighting takes the light's features, one without takes none")
        films = []
        if light is not None:
            params, at = self.film(light.to(x.device)).float(), 0
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
        return self.head(F.silu(h))

    def correction(self, x: torch.Tensor, panoramas: torch.Tensor | None = None) -> torch.Tensor:
        """The corrections [B,6|10,H,W] for network input `x` [B,9|15,H,W] (`network_input`) and, for a
        refiner with lighting, the target's camera-frame panoramas [B,h,w,3]: the network's own, or with
        `flip_average` the mean of it and the mirror image's (under the mirrored light) flipped back."""
        if self.config.lighting and panoramas is None:
            raise ValueError("this refiner sees the light; pass the target's camera-frame panoramas")
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

