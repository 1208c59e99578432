"""PyTorch reference of the DeepStereo network, layer for layer the candle model.

The Rust code (`deepstereo-core/src/model.rs`, `config.rs`) is the specification; this file
mirrors it so that one safetensors file loads in both: module and attribute names equal the
tensor names (`select.levels.{l}.{i}.weight`, `select.merge.{i}.bias`,
`select.depth.{i}.weight`, `select.log_scale`, `colour.levels...`, `colour.merge...`,
`colour.out...`), and loading is strict (a missing or unexpected tensor, or a wrong shape,
is an error). The configuration is the JSON of `deepstereo_core::config::Config` stored in
the file's metadata under `deepstereo.config`.

Shapes: input level `l` is `[B, D, 4V, H_l, W_l]` (the paper's family) or
`[B, D, V, 4, H_l, W_l]` (the any-number-of-views family, config `pool`, any V: its view
pooling and colour blend mirror `deepstereo-core/src/pool.rs`, tensors `views.encode.{i}.*`
and `colour.blend.{i}.*`; with `pool.cue` or `pool.weigh`, `[B, D, V, 4 + 5, H_l, W_l]`:
each view's geometric cue after its RGBA, `deepstereo-core/src/sweep/cue.rs`, read by the
encoder (`cue`) or by `views.weigh.{i}.*`, which weighs each view's alpha (`weigh`));
outputs `image` `[B, 3, th, tw]` and `selection` `[B, D, th, tw]`, with `th = H_0 - 2 pad(0)`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

CONFIG_KEY = "deepstereo.config"
FORMAT_KEY = "format"
FORMAT_VALUE = "deepstereo-weights-v1"
INIT_LOG_SCALE = 2.3
# pool.rs constants.
POOL_EPS = 1e-6
BLEND_EPS = 1e-12
BLEND_LOGIT_BOUND = 20.0
ENCODER_IN = 7
CUE_CHANNELS = 5
WEIGH_SCALE = 4.0  # config.rs: the cue's view weights are 1 + tanh(WEIGH_SCALE g)


# --- configuration (mirrors config.rs) -------------------------------------------------


@dataclass
class Conv:
    kernel: int
    channels: int


@dataclass
class TowerConfig:
    levels: int
    level_convs: list[Conv]
    merge_convs: list[Conv]

    @staticmethod
    def from_json(d: dict[str, Any]) -> "TowerConfig":
        return TowerConfig(
            levels=int(d["levels"]),
            level_convs=[Conv(int(c["kernel"]), int(c["channels"])) for c in d["level_convs"]],
            merge_convs=[Conv(int(c["kernel"]), int(c["channels"])) for c in d["merge_convs"]],
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "levels": self.levels,
            "level_convs": [c.__dict__ for c in self.level_convs],
            "merge_convs": [c.__dict__ for c in self.merge_convs],
        }

    def level_reduction(self) -> int:
        return sum(c.kernel - 1 for c in self.level_convs)

    def merge_reduction(self) -> int:
        return sum(c.kernel - 1 for c in self.merge_convs)

    def level_channels(self, in_channels: int) -> int:
        return self.level_convs[-1].channels if self.level_convs else in_channels

    def out_channels(self, in_channels: int) -> int:
        if self.merge_convs:
            return self.merge_convs[-1].channels
        return self.level_channels(in_channels) * self.levels

    def pad(self, l: int) -> int:
        rf = self.merge_reduction()
        return -(-rf // (1 << (l + 1))) + self.level_reduction() // 2

    def upsample_crop(self, l: int) -> int:
        rf = self.merge_reduction()
        return (1 << l) * -(-rf // (1 << (l + 1))) - rf // 2


@dataclass
class ViewPool:
    encoder: list[Conv]
    blend: list[Conv]
    # `pool.falloff` ({"full", "power"}): the inputs' alpha already carries the per-view
    # weights (deepstereo-core/src/view_weights.rs), so the network ignores it; kept so
    # that a config round-trips.
    falloff: dict[str, int] | None = None
    # `pool.cue`: each view's geometric cue follows its RGBA in the inputs and the encoder
    # reads it.
    cue: bool = False
    # `pool.weigh` (hidden widths): the cue follows the RGBA in the inputs and weighs each
    # view's alpha by `1 + tanh(WEIGH_SCALE g(cue))` (`views.weigh.*`); exclusive with `cue`.
    weigh: list[Conv] | None = None
    # `pool.agree` ({"near", "sigma"}): like the falloff, applied to the inputs' alpha by
    # whoever builds them (deepstereo-core/src/view_weights.rs, agree_gate); kept so that
    # a config round-trips.
    agree: dict[str, Any] | None = None
    # `pool.disagree` ({"near"}): one more cue channel, the view's colour disagreement with
    # the nearest views, computed by whoever builds the inputs
    # (deepstereo-core/src/view_weights.rs, disagreement) and read by `views.weigh.*`.
    disagree: dict[str, int] | None = None
    # `pool.features` ({"convs"}): the per-source CNN (`features.*`, deepstereo-core/src/features.rs),
    # whose maps, warped by whoever builds the inputs, follow each view's RGBA and cue and
    # are read by the encoder.
    source_features: list[Conv] | None = None

    @staticmethod
    def from_json(d: dict[str, Any]) -> "ViewPool":
        f = d.get("falloff")
        return ViewPool(
            encoder=[Conv(int(c["kernel"]), int(c["channels"])) for c in d["encoder"]],
            blend=[Conv(int(c["kernel"]), int(c["channels"])) for c in d["blend"]],
            falloff=None if f is None else {"full": int(f["full"]), "power": int(f["power"])},
            cue=bool(d.get("cue", False)),
            weigh=None if d.get("weigh") is None else [Conv(int(c["kernel"]), int(c["channels"])) for c in d["weigh"]],
            agree=None if d.get("agree") is None else {"near": int(d["agree"]["near"]), "sigma": float(d["agree"]["sigma"])},
            disagree=None if d.get("disagree") is None else {"near": int(d["disagree"]["near"])},
            source_features=None if d.get("features") is None else [Conv(int(c["kernel"]), int(c["channels"])) for c in d["features"]["convs"]],
        )

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {"encoder": [c.__dict__ for c in self.encoder], "blend": [c.__dict__ for c in self.blend]}
        if self.falloff is not None:
            d["falloff"] = dict(self.falloff)
        if self.cue:
            d["cue"] = True
        if self.weigh is not None:
            d["weigh"] = [c.__dict__ for c in self.weigh]
        if self.agree is not None:
            d["agree"] = dict(self.agree)
        if self.disagree is not None:
            d["disagree"] = dict(self.disagree)
        if self.source_features is not None:
            d["features"] = {"convs": [c.__dict__ for c in self.source_features]}
        return d

    def cue_channels(self) -> int:
        return CUE_CHANNELS + (1 if self.disagree is not None else 0)

    def feature_channels(self) -> int:
        """`F`: channels of each view's warped source features (0 without them)."""
        return self.source_features[-1].channels if self.source_features else 0

    def feature_radius(self) -> int:
        """`R`: the border each side the feature CNN's valid convolutions consume."""
        return sum(c.kernel // 2 for c in self.source_features or [])

    def encoder_in(self) -> int:
        return ENCODER_IN + (CUE_CHANNELS if self.cue else 0) + self.feature_channels()

    def encoder_view_channels(self) -> int:
        """Channels of a view the encoder reads: RGBA, the cue with `cue`, the features."""
        return 4 + (CUE_CHANNELS if self.cue else 0) + self.feature_channels()

    def view_channels(self) -> int:
        return 4 + (self.cue_channels() if self.cue or self.weigh is not None else 0) + self.feature_channels()

    def features(self) -> int:
        return self.encoder[-1].channels if self.encoder else self.encoder_in()

    def pooled_channels(self) -> int:
        return 4 + 2 * self.features()


@dataclass
class Config:
    name: str
    views: int
    planes: int
    levels: int
    tile: int
    select: TowerConfig
    depth_convs: list[Conv]
    colour: TowerConfig
    colour_skip: bool
    pool: ViewPool | None = None

    @staticmethod
    def from_json(d: dict[str, Any] | str) -> "Config":
        if isinstance(d, str):
            d = json.loads(d)
        cfg = Config(
            name=str(d["name"]),
            views=int(d["views"]),
            planes=int(d["planes"]),
            levels=int(d["levels"]),
            tile=int(d["tile"]),
            select=TowerConfig.from_json(d["select"]),
            depth_convs=[Conv(int(c["kernel"]), int(c["channels"])) for c in d["depth_convs"]],
            colour=TowerConfig.from_json(d["colour"]),
            colour_skip=bool(d["colour_skip"]),
            pool=ViewPool.from_json(d["pool"]) if d.get("pool") is not None else None,
        )
        cfg.validate()
        return cfg

    def to_json(self) -> str:
        d = {
            "name": self.name,
            "views": self.views,
            "planes": self.planes,
            "levels": self.levels,
            "tile": self.tile,
            "select": self.select.to_json(),
            "depth_convs": [c.__dict__ for c in self.depth_convs],
            "colour": self.colour.to_json(),
            "colour_skip": self.colour_skip,
        }
        if self.pool is not None:
            d["pool"] = self.pool.to_json()
        return json.dumps(d)

    def validate(self) -> None:
        if self.views <= 0 or self.planes <= 0:
            raise ValueError("views and planes must be positive")
        if not 1 <= self.levels <= 6:
            raise ValueError(f"levels must be 1..=6, got {self.levels}")
        for name, t in (("select", self.select), ("colour", self.colour)):
            if not 1 <= t.levels <= self.levels:
                raise ValueError(f"{name}.levels must be 1..={self.levels}, got {t.levels}")
            convs = t.level_convs + t.merge_convs + (self.depth_convs if name == "select" else [])
            for c in convs:
                if c.kernel % 2 == 0 or c.channels <= 0:
                    raise ValueError(f"{name}: kernels must be odd and channels positive, got {c}")
        if not self.depth_convs or self.depth_convs[-1].channels != 1:
            raise ValueError("the last depth conv must have 1 channel")
        if self.tile <= 0 or self.tile % self.tile_align() != 0:
            raise ValueError(f"tile {self.tile} must be a positive multiple of {self.tile_align()}")
        if self.pool is not None:
            for c in self.pool.encoder + self.pool.blend + (self.pool.weigh or []):
                if c.kernel != 1 or c.channels <= 0:
                    raise ValueError(f"pool: encoder, blend and weigh layers must be 1x1, got {c}")
            if self.pool.cue and self.pool.weigh is not None:
                raise ValueError("pool: cue and weigh are exclusive")
            if self.pool.disagree is not None and self.pool.weigh is None:
                raise ValueError("pool.disagree needs pool.weigh (the view weights read it)")
            for c in self.pool.source_features or []:
                if c.kernel % 2 == 0 or c.channels <= 0:
                    raise ValueError(f"pool.features: kernels must be odd and channels positive, got {c}")
            if self.colour_skip:
                raise ValueError("pool: colour_skip must be false")

    def in_channels(self) -> int:
        return 4 * self.views

    def tower_in_channels(self) -> int:
        return self.pool.pooled_channels() if self.pool is not None else self.in_channels()

    def tile_align(self) -> int:
        return 1 << (self.levels - 1)

    def pad(self, l: int) -> int:
        pads = [t.pad(l) for t in (self.select, self.colour) if l < t.levels]
        return max(pads) if pads else 0

    def input_size(self, l: int, t: int) -> int:
        return (t >> l) + 2 * self.pad(l)

    # The presets of config.rs (`Config::paper`, `tiny`, `nviews`, `Config::preset`).
    @staticmethod
    def paper() -> "Config":
        tower = TowerConfig(4, [Conv(5, 96), Conv(3, 48), Conv(3, 16)], [Conv(5, 96), Conv(5, 64), Conv(3, 32)])
        return Config(
            name="paper",
            views=5,
            planes=96,
            levels=4,
            tile=8,
            select=tower,
            depth_convs=[Conv(3, 32), Conv(3, 16), Conv(3, 1)],
            colour=TowerConfig(4, list(tower.level_convs), list(tower.merge_convs)),
            colour_skip=False,
        )

    @staticmethod
    def tiny() -> "Config":
        return Config(
            name="tiny",
            views=4,
            planes=32,
            levels=2,
            tile=24,
            select=TowerConfig(2, [Conv(3, 12), Conv(3, 12)], [Conv(3, 16), Conv(3, 12)]),
            depth_convs=[Conv(3, 12), Conv(3, 8), Conv(3, 1)],
            colour=TowerConfig(1, [Conv(1, 12)], [Conv(1, 12)]),
            colour_skip=True,
        )

    @staticmethod
    def nviews() -> "Config":
        return Config(
            name="nviews",
            views=6,
            planes=32,
            levels=3,
            tile=24,
            select=TowerConfig(3, [Conv(3, 12), Conv(3, 12)], [Conv(3, 12), Conv(3, 12)]),
            depth_convs=[Conv(3, 12), Conv(3, 6), Conv(3, 1)],
            colour=TowerConfig(1, [Conv(1, 12)], []),
            colour_skip=False,
            pool=ViewPool(encoder=[Conv(1, 6), Conv(1, 6)], blend=[Conv(1, 6)], falloff={"full": 4, "power": 8}),
        )

    @staticmethod
    def nviews_cue() -> "Config":
        c = Config.nviews()
        c.name = "nviews-cue"
        assert c.pool is not None
        c.pool.cue = True
        c.pool.falloff = {"full": 1, "power": 2}
        return c

    @staticmethod
    def nviews_weigh() -> "Config":
        c = Config.nviews()
        c.name = "nviews-weigh"
        assert c.pool is not None
        c.pool.weigh = [Conv(1, 8)]
        c.pool.falloff = {"full": 1, "power": 2}
        return c

    @staticmethod
    def nviews_disagree() -> "Config":
        c = Config.nviews_weigh()
        c.name = "nviews-disagree"
        assert c.pool is not None
        c.pool.disagree = {"near": 4}
        return c

    @staticmethod
    def nviews_features() -> "Config":
        c = Config.nviews_disagree()
        c.name = "nviews-features"
        assert c.pool is not None
        c.pool.source_features = [Conv(3, 12), Conv(3, 12), Conv(3, 8)]
        c.pool.encoder = [Conv(1, 8), Conv(1, 6)]
        return c

    @staticmethod
    def preset(name: str) -> "Config | None":
        """A preset by name (`PRESETS`), or None."""
        presets = {
            "paper": Config.paper,
            "tiny": Config.tiny,
            "nviews": Config.nviews,
            "nviews-cue": Config.nviews_cue,
            "nviews-weigh": Config.nviews_weigh,
            "nviews-disagree": Config.nviews_disagree,
            "nviews-features": Config.nviews_features,
        }
        return presets.get(name, lambda: None)()


PRESETS = ("tiny", "paper", "nviews", "nviews-cue", "nviews-weigh", "nviews-disagree", "nviews-features")


# --- the network (mirrors model.rs) ----------------------------------------------------


def upsample_nearest(x: torch.Tensor, s: int) -> torch.Tensor:
    """`[N, C, H, W]` -> `[N, C, sH, sW]`, as model.rs (reshape and broadcast)."""
    n, c, h, w = x.shape
    return x.reshape(n, c, h, 1, w, 1).expand(n, c, h, s, w, s).reshape(n, c, h * s, w * s)


class Tower(nn.Module):
    """The 2D part of a tower: per-level convs (shared across planes), upsampling, merge."""

    def __init__(self, cfg: TowerConfig, in_channels: int):
        super().__init__()
        self.cfg = cfg
        self.levels = nn.ModuleList()
        for _ in range(cfg.levels):
            convs = nn.ModuleList()
            ch = in_channels
            for c in cfg.level_convs:
                convs.append(nn.Conv2d(ch, c.channels, c.kernel))
                ch = c.channels
            self.levels.append(convs)
        self.merge = nn.ModuleList()
        ch = cfg.level_channels(in_channels) * cfg.levels
        for c in cfg.merge_convs:
            self.merge.append(nn.Conv2d(ch, c.channels, c.kernel))
            ch = c.channels

    def tower_forward(self, inputs: list[torch.Tensor], th: int, tw: int) -> torch.Tensor:
        rf = self.cfg.merge_reduction()
        feats = []
        for l, convs in enumerate(self.levels):
            x = inputs[l]
            for conv in convs:
                x = F.relu(conv(x))
            if l > 0:
                x = upsample_nearest(x, 1 << l)
            off = self.cfg.upsample_crop(l)
            if x.shape[2] < off + th + rf or x.shape[3] < off + tw + rf:
                raise ValueError(f"level {l} features {tuple(x.shape)} too small for the tile")
            feats.append(x[:, :, off : off + th + rf, off : off + tw + rf])
        x = torch.cat(feats, 1)
        for conv in self.merge:
            x = F.relu(conv(x))
        return x


class SelectTower(Tower):
    """`select.*`: the 2D tower, the convolutions along depth and `log_scale`."""

    def __init__(self, cfg: Config):
        super().__init__(cfg.select, cfg.tower_in_channels())
        self.depth = nn.ModuleList()
        ch = cfg.select.out_channels(cfg.tower_in_channels())
        for c in cfg.depth_convs:
            # Weights [C_out, C_in, k, 1]; zero padding along depth keeps D.
            self.depth.append(nn.Conv2d(ch, c.channels, (c.kernel, 1), padding=(c.kernel // 2, 0)))
            ch = c.channels
        self.log_scale = nn.Parameter(torch.full((1,), INIT_LOG_SCALE))


class ColourTower(Tower):
    """`colour.*`: the 2D tower and the linear RGB layer `out`; pooled, also `blend`."""

    def __init__(self, cfg: Config):
        super().__init__(cfg.colour, cfg.tower_in_channels())
        cin = cfg.tower_in_channels()
        cout_in = cfg.colour.out_channels(cin) + (cfg.in_channels() if cfg.colour_skip else 0)
        self.out = nn.Conv2d(cout_in, 3, 1)
        if cfg.pool is not None:
            self.blend = nn.ModuleList()
            ch = cfg.pool.features() + cfg.colour.out_channels(cin)
            for cout in [c.channels for c in cfg.pool.blend] + [1]:
                self.blend.append(nn.Conv2d(ch, cout, 1))
                ch = cout

    def blend_forward(self, e: torch.Tensor, x: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
        """`Blend::forward`: e `[N, V, C_f, th, tw]`, x (RGBA) `[N, V, 4, th, tw]`, f
        `[N, C_c, th, tw]` -> `[N, 3, th, tw]`."""
        n, v, cf, th, tw = e.shape
        y = torch.cat([e, f.unsqueeze(1).expand(n, v, f.shape[1], th, tw)], 2).reshape(n * v, -1, th, tw)
        last = len(self.blend) - 1
        for i, conv in enumerate(self.blend):
            y = conv(y)
            if i < last:
                y = F.relu(y)
        logits = torch.tanh(y.reshape(n, v, 1, th, tw) / BLEND_LOGIT_BOUND) * BLEND_LOGIT_BOUND
        rgb, a = x[:, :, :3], x[:, :, 3:4]
        ex = torch.exp(logits) * a
        w = ex / (ex.sum(1, keepdim=True) + BLEND_EPS)
        return (rgb * w).sum(1)


class Views(nn.Module):
    """`views.*`: the per-view encoder and the alpha-weighted pooling (`pool.rs`)."""

    def __init__(self, pool: ViewPool):
        super().__init__()
        self.cue = pool.cue
        self.cue_channels = pool.cue_channels()
        self.feature_channels = pool.feature_channels()
        self.encoder_view_channels = pool.encoder_view_channels()
        self.encode = nn.ModuleList()
        ch = pool.encoder_in()
        for c in pool.encoder:
            self.encode.append(nn.Conv2d(ch, c.channels, 1))
            ch = c.channels
        if pool.weigh is not None:
            self.weigh = nn.ModuleList()
            ch = self.cue_channels
            for cout in [c.channels for c in pool.weigh] + [1]:
                self.weigh.append(nn.Conv2d(ch, cout, 1))
                ch = cout

    def weigh_forward(self, x: torch.Tensor) -> torch.Tensor:
        """`ViewWeigh::forward`: `[B, D, V, 4 + K, H, W]` -> `[B, D, V, 4, H, W]` (`K` 5, or 6
        with `pool.disagree`), each view's RGB and its alpha times `1 + tanh(WEIGH_SCALE g(cue))`."""
        b, d, v, cv, h, w = x.shape
        k = self.cue_channels
        f = self.feature_channels
        if cv != 4 + k + f:
            raise ValueError(f"expected [B, D, V, {4 + k + f}, H, W], got {tuple(x.shape)}")
        g = x[:, :, :, 4 : 4 + k].reshape(b * d * v, k, h, w)
        last = len(self.weigh) - 1
        for i, conv in enumerate(self.weigh):
            g = conv(g)
            if i < last:
                g = F.relu(g)
        k = (2.0 * torch.sigmoid(g * (2.0 * WEIGH_SCALE))).reshape(b, d, v, 1, h, w)  # = 1 + tanh(S g), accurate where small
        return torch.cat([x[:, :, :, :3], x[:, :, :, 3:4] * k, x[:, :, :, 4 + self.cue_channels :]], 3)

    def pool_forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """`ViewEncoder::forward`: `[B, D, V, C_v, H, W]` (`C_v` 4, or 4 + 5 with the cue)
        -> (stats `[B, D, 4 + 2 C_f, H, W]`, features `[B*D, V, C_f, H, W]`)."""
        b, d, v, cv, h, w = x.shape
        want = self.encoder_view_channels
        if cv != want:
            raise ValueError(f"expected [B, D, V, {want}, H, W], got {tuple(x.shape)}")
        x = x.reshape(b * d, v, cv, h, w)
        cue = x[:, :, 4:]
        x = x[:, :, :4]
        rgb, a = x[:, :, :3], x[:, :, 3:4]
        asum = a.sum(1, keepdim=True)
        den = asum + POOL_EPS
        mean_rgb = (rgb * a).sum(1, keepdim=True) / den
        e = torch.cat([x, rgb - mean_rgb, cue], 2).reshape(b * d * v, -1, h, w)
        for conv in self.encode:
            e = F.relu(conv(e))
        e = e.reshape(b * d, v, -1, h, w)
        mean_e = (e * a).sum(1, keepdim=True) / den
        var_e = ((e - mean_e) ** 2 * a).sum(1, keepdim=True) / den
        cover = asum / (asum + 1.0)
        stats = torch.cat([mean_rgb, cover, mean_e, var_e], 2).reshape(b, d, -1, h, w)
        return stats, e


class DeepStereo(nn.Module):
    def __init__(self, cfg: Config):
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        self.select = SelectTower(cfg)
        self.colour = ColourTower(cfg)
        if cfg.pool is not None:
            self.views = Views(cfg.pool)
            if cfg.pool.source_features:
                # `features.*`: the per-source CNN (`FeatureNet`, deepstereo-core/src/features.rs).
                self.features = nn.ModuleList()
                ch = 3
                for c in cfg.pool.source_features:
                    self.features.append(nn.Conv2d(ch, c.channels, c.kernel))
                    ch = c.channels

    def warped_features(self, levels: list[torch.Tensor], warps: list[dict]) -> list[torch.Tensor]:
        """Training's inputs of the features family (`inputs/features.rs`,
        `with_warped_features`): `levels[l]` `[B, D, V, C_b, H, W]` (without the features)
        with every sample's warped maps appended, `[B, D, V, C_b + F, H, W]`. `warps[b]`
        maps `(l, v)` to sample `b`'s `(crop [3, h + 2R, w + 2R], index [D*P, 4] int64,
        weight [D*P, 4])` (`deepstereo samples`' `warp.*` tensors); a view it lacks gets
        zeros. Differentiable in the CNN's weights."""
        f = self.cfg.pool.feature_channels()
        out = []
        for l, x in enumerate(levels):
            b, d, v, _, h, w = x.shape
            samples = []
            for k in range(b):
                views = []
                for j in range(v):
                    if (l, j) in warps[k]:
                        crop, index, weight = warps[k][(l, j)]
                        fm = self.features_forward(crop[None])[0].reshape(f, -1)  # [F, h_f * w_f]
                        g = (fm[:, index] * weight).sum(-1)  # [F, D*P]
                        views.append(g.reshape(f, d, h * w).transpose(0, 1))  # [D, F, P]
                    else:
                        views.append(x.new_zeros(d, f, h * w))
                samples.append(torch.stack(views, 1))  # [D, V, F, P]
            feats = torch.stack(samples, 0).reshape(b, d, v, f, h, w)
            out.append(torch.cat([x, feats], 3))
        return out

    def features_forward(self, image: torch.Tensor) -> torch.Tensor:
        """`FeatureNet::forward`: source images zero-padded by `R`, `[N, 3, H + 2R, W + 2R]`
        -> `[N, F, H, W]` (valid convolutions, ReLU after all but the last)."""
        x = image
        last = len(self.features) - 1
        for i, conv in enumerate(self.features):
            x = conv(x)
            if i < last:
                x = F.relu(x)
        return x

    def _folded(self, inputs: list[torch.Tensor], t: TowerConfig) -> list[torch.Tensor]:
        cfg = self.cfg
        out = []
        for l in range(t.levels):
            x = inputs[l]
            b, d, c, h, w = x.shape
            off = cfg.pad(l) - t.pad(l)
            out.append(x[:, :, :, off : h - off, off : w - off].reshape(b * d, c, h - 2 * off, w - 2 * off))
        return out

    def forward(self, inputs: list[torch.Tensor], warps: list[dict] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """`inputs[l]`: the sweep levels; for the features family either with the warped
        maps among each view's channels, or without them and with training's `warps`
        ([`warped_features`])."""
        cfg = self.cfg
        if warps is not None:
            inputs = self.warped_features(inputs, warps)
        if len(inputs) != cfg.levels:
            raise ValueError(f"expected {cfg.levels} input levels, got {len(inputs)}")
        if cfg.pool is not None and cfg.pool.weigh is not None:
            inputs = [self.views.weigh_forward(x) for x in inputs]
        raw = inputs
        features = None
        if cfg.pool is not None:
            pooled = [self.views.pool_forward(x) for x in inputs]
            inputs = [p[0] for p in pooled]
            features = pooled[0][1]
        b, d, cin, h0, w0 = inputs[0].shape
        if cin != cfg.tower_in_channels():
            raise ValueError(f"expected {cfg.tower_in_channels()} input channels, got {cin}")
        th, tw = h0 - 2 * cfg.pad(0), w0 - 2 * cfg.pad(0)
        # Selection tower.
        s = self.select.tower_forward(self._folded(inputs, cfg.select), th, tw)  # [B*D, C, th, tw]
        c = s.shape[1]
        x = s.reshape(b, d, c, th * tw).transpose(1, 2)  # [B, C, D, th*tw]
        last = len(self.select.depth) - 1
        for i, conv in enumerate(self.select.depth):
            x = conv(x)
            if i < last:
                x = F.relu(x)
        logits = torch.tanh(x) * torch.exp(self.select.log_scale)  # [B, 1, D, th*tw]
        selection = torch.softmax(logits, 2).reshape(b, d, th, tw)
        # Colour tower.
        f = self.colour.tower_forward(self._folded(inputs, cfg.colour), th, tw)  # [B*D, C, th, tw]
        if features is not None:
            p = cfg.pad(0)
            x0 = raw[0].reshape(b * d, raw[0].shape[2], -1, h0, w0)[:, :, :4, p : p + th, p : p + tw]
            e0 = features[:, :, :, p : p + th, p : p + tw]
            colours = self.colour.blend_forward(e0, x0, f) + self.colour.out(f)
            image = (colours.reshape(b, d, 3, th, tw) * selection.unsqueeze(2)).sum(1)
            return image, selection
        if cfg.colour_skip:
            p = cfg.pad(0)
            centre = inputs[0][:, :, :, p : p + th, p : p + tw].reshape(b * d, cin, th, tw)
            f = torch.cat([f, centre], 1)
        colours = self.colour.out(f).reshape(b, d, 3, th, tw)
        image = (colours * selection.unsqueeze(2)).sum(1)  # [B, 3, th, tw]
        return image, selection


# --- files ----------------------------------------------------------------------------


def read_config(path: str) -> Config:
    from safetensors import safe_open

    with safe_open(path, framework="pt") as f:
        meta = f.metadata() or {}
    if CONFIG_KEY not in meta:
        raise ValueError(f"{path}: no '{CONFIG_KEY}' in the metadata: not a deepstereo weights file")
    return Config.from_json(meta[CONFIG_KEY])


def load(path: str) -> DeepStereo:
    """Loads a weights file strictly (any missing or unexpected tensor is an error)."""
    from safetensors.torch import load_file

    model = DeepStereo(read_config(path))
    state = load_file(path)
    for k, v in state.items():
        if v.dtype != torch.float32:
            raise ValueError(f"{path}: tensor '{k}' is {v.dtype}, expected float32")
        if not torch.isfinite(v).all():
            raise ValueError(f"{path}: tensor '{k}' holds non-finite values")
    model.load_state_dict(state, strict=True)
    model.eval()
    return model


def init_weights(cfg: Config, path: str, seed: int = 0) -> None:
    """Writes a freshly initialised model of `cfg` (PyTorch's default init) in the Rust
    weights format."""
    from safetensors.torch import save_file

    torch.manual_seed(seed)
    model = DeepStereo(cfg)
    state = {k: v.detach().contiguous() for k, v in model.state_dict().items()}
    save_file(state, path, metadata={CONFIG_KEY: cfg.to_json(), FORMAT_KEY: FORMAT_VALUE})


def parameter_count(model: nn.Module) -> int:
    return sum(math.prod(p.shape) for p in model.parameters())
