"""PyTorch reference of the DeepStereo network, layer for layer the candle model.

The Rust code (`deepstereo-core/src/model.rs`, `config.rs`) is the specification; this file
mirrors it so that one safetensors file loads in both: module and attribute names equal the
tensor names (`select.levels.{l}.{i}.weight`, `select.merge.{i}.bias`,
`select.depth.{i}.weight`, `select.log_scale`, `colour.levels...`, `colour.merge...`,
`colour.out...`), and loading is strict (a missing or unexpected tensor, or a wrong shape,
is an error). The configuration is the JSON of `deepstereo_core::config::Config` stored in
the file's metadata under `deepstereo.config`.

Shapes: input level `l` is `[B, D, 4V, H_l, W_l]`; outputs `image` `[B, 3, th, tw]` and
`selection` `[B, D, th, tw]`, with `th = H_0 - 2 pad(0)`.
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
        )
        cfg.validate()
        return cfg

    def to_json(self) -> str:
        return json.dumps(
            {
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
        )

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

    def in_channels(self) -> int:
        return 4 * self.views

    def tile_align(self) -> int:
        return 1 << (self.levels - 1)

    def pad(self, l: int) -> int:
        pads = [t.pad(l) for t in (self.select, self.colour) if l < t.levels]
        return max(pads) if pads else 0

    def input_size(self, l: int, t: int) -> int:
        return (t >> l) + 2 * self.pad(l)


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
        super().__init__(cfg.select, cfg.in_channels())
        self.depth = nn.ModuleList()
        ch = cfg.select.out_channels(cfg.in_channels())
        for c in cfg.depth_convs:
            # Weights [C_out, C_in, k, 1]; zero padding along depth keeps D.
            self.depth.append(nn.Conv2d(ch, c.channels, (c.kernel, 1), padding=(c.kernel // 2, 0)))
            ch = c.channels
        self.log_scale = nn.Parameter(torch.full((1,), INIT_LOG_SCALE))


class ColourTower(Tower):
    """`colour.*`: the 2D tower and the linear RGB layer `out`."""

    def __init__(self, cfg: Config):
        super().__init__(cfg.colour, cfg.in_channels())
        cin = cfg.in_channels()
        cout_in = cfg.colour.out_channels(cin) + (cin if cfg.colour_skip else 0)
        self.out = nn.Conv2d(cout_in, 3, 1)


class DeepStereo(nn.Module):
    def __init__(self, cfg: Config):
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        self.select = SelectTower(cfg)
        self.colour = ColourTower(cfg)

    def _folded(self, inputs: list[torch.Tensor], t: TowerConfig) -> list[torch.Tensor]:
        cfg = self.cfg
        out = []
        for l in range(t.levels):
            x = inputs[l]
            b, d, c, h, w = x.shape
            off = cfg.pad(l) - t.pad(l)
            out.append(x[:, :, :, off : h - off, off : w - off].reshape(b * d, c, h - 2 * off, w - 2 * off))
        return out

    def forward(self, inputs: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        cfg = self.cfg
        if len(inputs) != cfg.levels:
            raise ValueError(f"expected {cfg.levels} input levels, got {len(inputs)}")
        b, d, cin, h0, w0 = inputs[0].shape
        if cin != cfg.in_channels():
            raise ValueError(f"expected {cfg.in_channels()} input channels, got {cin}")
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
