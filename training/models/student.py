"""Stage II video students.

`streaming`: each frame is encoded once on its own by a small 2D CNN (cheap on a robot CPU); a
small transformer with learned time embeddings reads the embeddings of up to 25 frames (a valid
mask marks observed ones), so a new frame costs one frame encoding plus a tiny temporal head.

`uniformer`: a UniFormer-XXS-style clip encoder like the paper's: 3D conv stem, local MHRA
(depthwise 3D conv relation aggregators) in the early stages, global self-attention in the late
ones. Input is the full 25-frame clip; unobserved frames are zeroed by the valid mask.
"""
from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

from ad_estimator.model import MASK_LEVELS
from training.models.common import Heads, Transformer, masked_pool

FRAME_COUNT = 25


@dataclass
class StudentConfig:
    kind: str = "streaming"  # streaming | uniformer
    input_size: tuple[int, int] = (64, 64)
    z_dim: int = 256  # must match the teacher's
    # streaming
    channels: tuple[int, ...] = (16, 32, 64, 96)
    pool: int = 4  # the last feature map is average-pooled to pool x pool, then flattened
    embed_dim: int = 128
    # Shape moments of each frame (area, centroid, spread, bottom and top) join the CNN features:
    # a jelly's stiffness shows as a few pixels of squash and rebound, which pooled CNN features
    # blur. False for models trained before they existed.
    moments: bool = False
    # The frame encoder also sees this many earlier observed frames (extra input channels, newest
    # first), so the CNN can compare consecutive masks pixel by pixel before pooling blurs a few
    # pixels of squash, and with two or more see acceleration. 0 for models trained before it existed.
    previous_frames: int = 0
    # What a mask pixel holds: binary (0/255, the simulator's default) or coverage (its area coverage
    # 0..255, bags from ad_sim.generate --coverage-masks), which keeps each edge to a fraction of a pixel.
    mask_levels: str = "binary"
    temporal_width: int = 128
    temporal_depth: int = 2
    temporal_heads: int = 4
    # uniformer
    dims: tuple[int, ...] = (32, 64, 128, 256)
    depths: tuple[int, ...] = (1, 2, 2, 1)
    global_stages: int = 2  # the last stages use global attention
    dropout: float = 0.1

    def __post_init__(self):
        # Every way of making a config (presets, --set, a checkpoint's meta) is checked here, so that a
        # bad value is one line naming the field, not a ZeroDivisionError or a torch error (after the data
        # loaded, or after training a model that cannot be exported).
        for field in dataclasses.fields(self):
            if problem := field_problem(field.name, getattr(self, field.name)):
                raise ValueError(problem)
        if self.kind == "streaming" and self.temporal_width % self.temporal_heads:
            raise ValueError(f"temporal_width {self.temporal_width} is not divisible by temporal_heads "
                             f"{self.temporal_heads}")
        if self.kind == "uniformer" and len(self.dims) != len(self.depths):
            # zip() would silently drop the stages that one of them lacks
            raise ValueError(f"dims {self.dims} and depths {self.depths} must have one entry per stage each")

    def to_dict(self) -> dict:
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict) -> "StudentConfig":
        d = dict(d)
        if "previous_frame" in d:  # checkpoints before previous_frames: a flag for one previous frame
            d["previous_frames"] = int(d.pop("previous_frame"))
        if unknown := sorted(set(d) - {f.name for f in dataclasses.fields(cls)}):  # a ValueError, not a TypeError
            raise ValueError(f"unknown config field{'s' * (len(unknown) > 1)} {', '.join(map(repr, unknown))}")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


# What each field of StudentConfig may hold (field_problem): sizes are whole numbers >= 1, counts >= 0.
_SIZES = ("z_dim", "pool", "embed_dim", "temporal_width", "temporal_heads")
_COUNTS = ("previous_frames", "temporal_depth", "global_stages")


def _whole(value, least: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= least


def field_problem(name: str, value) -> str | None:
    """Why `value` cannot be StudentConfig's field `name` (one line naming it), or None if it can."""
    if name == "kind" and value not in ("streaming", "uniformer"):
        return f"kind is streaming or uniformer, got {value!r}"
    if name == "mask_levels" and value not in MASK_LEVELS:
        return f"mask_levels is one of {', '.join(MASK_LEVELS)}, got {value!r}"
    if name in _SIZES and not _whole(value, 1):
        return f"{name} must be a whole number >= 1, got {value!r}"
    if name in _COUNTS and not _whole(value, 0):
        return f"{name} must be a whole number >= 0, got {value!r}"
    if name == "input_size" and not (isinstance(value, (tuple, list)) and len(value) == 2
                                     and all(_whole(v, 1) for v in value)):
        return f"input_size must be two whole numbers >= 1 (height,width), got {value!r}"
    if name in ("channels", "dims") and not (isinstance(value, (tuple, list)) and value
                                             and all(_whole(v, 1) for v in value)):
        return f"{name} must be one or more whole numbers >= 1, got {value!r}"
    if name == "depths" and not (isinstance(value, (tuple, list)) and value and all(_whole(v, 0) for v in value)):
        return f"depths must be one or more whole numbers >= 0, got {value!r}"
    if name == "dropout" and not (isinstance(value, (int, float)) and not isinstance(value, bool)
                                  and 0.0 <= value < 1.0):
        return f"dropout must be a number in [0, 1), got {value!r}"
    if name == "moments" and not isinstance(value, bool):
        return f"moments must be true or false, got {value!r}"
    return None


def override_config(config: StudentConfig, assignments: list[str]) -> StudentConfig:
    """Apply KEY=VALUE assignments (`--set` of `python -m training student`) to `config`: each value is
    read as the type of the field's current value (comma-separated for tuples, true/false for flags)."""
    fields = {f.name for f in dataclasses.fields(config)} - {"kind", "z_dim"}
    changes = {}
    for item in assignments:
        key, sep, text = item.partition("=")
        if not sep or key not in fields:
            raise ValueError(f"--set {item!r}: expected KEY=VALUE with KEY one of {', '.join(sorted(fields))}")
        current = getattr(config, key)
        try:
            if isinstance(current, bool):
                if text.lower() not in ("true", "false"):
                    raise ValueError
                changes[key] = text.lower() == "true"
            elif isinstance(current, tuple):
                changes[key] = tuple(type(current[0])(v) for v in text.split(","))
            else:
                changes[key] = type(current)(text)
        except ValueError:
            raise ValueError(f"--set {item!r}: {key} takes a value like {current!r}") from None
        if problem := field_problem(key, changes[key]):  # read as the right type, but out of range
            raise ValueError(f"--set {item!r}: {problem}")
    try:
        return dataclasses.replace(config, **changes)
    except ValueError as e:  # fields that do not go together (e.g. temporal_width and temporal_heads)
        raise ValueError(f"--set {' '.join(map(repr, assignments))}: {e}") from None


def student_preset(kind: str, size: str, z_dim: int) -> StudentConfig:
    """Model size presets: paper (GPU), small (2-core CPU in minutes), tiny (tests)."""
    if kind not in ("streaming", "uniformer"):
        raise ValueError(f"unknown student kind {kind!r}; expected streaming or uniformer")
    presets = {
        # 128x128: the masks' own size (measured: 0.51 ms per frame encoding on one robot CPU core,
        # 0.31 ms at 96x96; the temporal head dominates the per-frame cost anyway).
        ("streaming", "paper"): dict(input_size=(128, 128), channels=(16, 32, 64, 128), pool=4, embed_dim=192,
                                     temporal_width=192, temporal_depth=3, temporal_heads=6, moments=True),
        ("streaming", "small"): dict(channels=(12, 24, 48, 96), embed_dim=96, temporal_width=96, moments=True),
        ("streaming", "tiny"): dict(input_size=(32, 32), channels=(8, 16), embed_dim=32, temporal_width=32,
                                    temporal_depth=1, temporal_heads=2, dropout=0.0, moments=True),
        # UniFormer-XXS: dims 64-128-256-512, depths 2-5-8-2, 128x128 input.
        ("uniformer", "paper"): dict(input_size=(128, 128), dims=(64, 128, 256, 512), depths=(2, 5, 8, 2)),
        ("uniformer", "small"): dict(input_size=(64, 64)),
        ("uniformer", "tiny"): dict(input_size=(32, 32), dims=(8, 16), depths=(1, 1), global_stages=1,
                                    dropout=0.0),
    }
    if size not in ("paper", "small", "tiny"):
        raise ValueError(f"unknown model size {size!r}; expected paper, small or tiny")
    return StudentConfig(kind=kind, z_dim=z_dim, **presets[(kind, size)])


def _conv_bn(cin: int, cout: int, stride: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False), nn.BatchNorm2d(cout),
                         nn.ReLU(inplace=True))


MOMENT_COUNT = 8


def shape_moments(frame: torch.Tensor, xs: torch.Tensor, ys: torch.Tensor) -> torch.Tensor:
    """(B, 1, H, W) mask in [0, 1] -> (B, MOMENT_COUNT): area fraction, centroid (x, y), spread
    (std x, std y, xy covariance), and the lowest and highest covered rows, in image coordinates
    scaled to [-1, 1] (xs (1, 1, W) and ys (1, H, 1) hold them). An empty frame gives zeros."""
    f = frame[:, 0]
    mass = f.sum((1, 2))
    area = mass / (f.shape[1] * f.shape[2])
    total = mass.clamp(min=1e-6)
    cx = (f * xs).sum((1, 2)) / total
    cy = (f * ys).sum((1, 2)) / total
    dx, dy = xs - cx[:, None, None], ys - cy[:, None, None]
    sxx, syy = (f * dx * dx).sum((1, 2)) / total, (f * dy * dy).sum((1, 2)) / total
    sxy = (f * dx * dy).sum((1, 2)) / total
    covered = (f.amax(2) > 0.5).to(f.dtype)  # (B, H): rows with a covered pixel
    row_y = ys[:, :, 0]  # (1, H); image y grows downwards
    bottom = (covered * (row_y + 1.0)).amax(1) - 1.0
    top = (covered * (1.0 - row_y)).amax(1) - 1.0  # = -(y of the highest covered row)
    seen = (mass > 0).to(f.dtype)
    moments = torch.stack([area, cx, cy, sxx.clamp(min=0).sqrt(), syy.clamp(min=0).sqrt(), sxy, bottom, top], 1)
    return moments * seen[:, None]


class FrameEncoder(nn.Module):
    """(B, 1, H, W) in [0, 1] -> (B, D). Stride-2 conv stages, pooled to a small map (pool x pool)
    and flattened so the embedding keeps where the object is in the image (it falls and lands)."""

    def __init__(self, config: StudentConfig):
        super().__init__()
        side = [n / 2 ** len(config.channels) for n in config.input_size]
        if any(n < config.pool or n % config.pool for n in side):
            raise ValueError(f"input size {config.input_size} with {len(config.channels)} stride-2 stages leaves a "
                             f"{side} map; it must be a multiple of pool={config.pool} (exportable pooling)")
        layers, cin = [], frame_channels(config)
        last = len(config.channels) - 1
        for stage, cout in enumerate(config.channels):
            layers += [_conv_bn(cin, cout, 2), _conv_bn(cout, cout, 1)] if stage == last else [_conv_bn(cin, cout, 2)]
            cin = cout
        self.features = nn.Sequential(*layers)
        self.pool = nn.AdaptiveAvgPool2d(config.pool)
        self.moments = config.moments
        extra = MOMENT_COUNT if config.moments else 0
        h, w = config.input_size
        # Pixel coordinates in [-1, 1], fixed by the input size (not saved: nothing to learn).
        self.register_buffer("xs", torch.linspace(-1.0, 1.0, w).view(1, 1, w), persistent=False)
        self.register_buffer("ys", torch.linspace(-1.0, 1.0, h).view(1, h, 1), persistent=False)
        # (Flatten is a no-op on the flat input; it keeps the parameter names of older checkpoints.)
        self.project = nn.Sequential(nn.Flatten(), nn.Linear(cin * config.pool ** 2 + extra, config.embed_dim),
                                     nn.LayerNorm(config.embed_dim))

    def forward(self, frame: torch.Tensor) -> torch.Tensor:
        """frame (B, C, H, W): the mask, then its `previous_frames` earlier observed masks, newest first."""
        x = self.pool(self.features(frame)).flatten(1)
        if self.moments:
            # Moments are in [-1, 1]; x4 puts them on the scale of the CNN features.
            x = torch.cat([x, 4.0 * shape_moments(frame[:, :1], self.xs, self.ys)], 1)
        return self.project(x)


def frame_channels(config: StudentConfig) -> int:
    """Input channels of the streaming frame encoder: the mask and its earlier observed ones."""
    return 1 + config.previous_frames


def frame_encoder_input(config: StudentConfig, masks: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(B, T, H, W) masks, (B, T) valid -> (B, T, C, H, W): what the frame encoder reads for each
    slot, the mask and its `previous_frames` earlier observed masks, newest first."""
    if not config.previous_frames:
        return masks.unsqueeze(2)
    sources = earlier_observed_slots(valid, config.previous_frames)  # (B, T, n)
    frames = [masks] + [masks.gather(1, sources[:, :, k, None, None].expand_as(masks))
                        for k in range(config.previous_frames)]
    return torch.stack(frames, dim=2)


def earlier_observed_slots(valid: torch.Tensor, n: int) -> torch.Tensor:
    """(B, T) valid -> (B, T, n): for each slot, its n latest earlier valid slots, newest first.
    Where there are fewer, the oldest one available stands in (the episode's first frame; for
    that frame, itself: the first frame has no motion yet). The estimator's window follows the
    same rule (ad_estimator.model.EstimatorModel.encode)."""
    slots = torch.arange(valid.shape[1], device=valid.device).expand_as(valid)
    latest = torch.where(valid > 0, slots, -1).cummax(1).values  # the latest valid slot up to each slot
    latest = torch.cat([latest.new_full((len(valid), 1), -1), latest[:, :-1]], 1)  # ... before each slot
    previous = torch.where(latest >= 0, latest, slots)  # (B, T); a slot without one: itself
    sources = [previous]
    for _ in range(n - 1):  # the k-th previous is the previous of the (k-1)-th
        sources.append(previous.gather(1, sources[-1]))
    return torch.stack(sources, dim=-1)


class TemporalHead(nn.Module):
    """(B, T, D) frame embeddings + (B, T) valid mask -> heads. Token t sees its own embedding,
    the change from the previous frame and a learned embedding of its frame index."""

    def __init__(self, config: StudentConfig):
        super().__init__()
        w = config.temporal_width
        self.input = nn.Linear(2 * config.embed_dim, w)
        self.time = nn.Parameter(torch.zeros(1, FRAME_COUNT, w))
        nn.init.normal_(self.time, std=0.02)
        self.transformer = Transformer(w, config.temporal_depth, config.temporal_heads, config.dropout)
        self.heads = Heads(2 * w, w, config.z_dim)

    def forward(self, embeddings: torch.Tensor, valid: torch.Tensor) -> dict[str, torch.Tensor]:
        t = embeddings.shape[1]
        e = embeddings * valid.unsqueeze(-1)
        previous = torch.cat([e[:, :1], e[:, :-1]], dim=1)
        change = (e - previous) * valid.unsqueeze(-1)
        x = self.input(torch.cat([e, change], dim=-1)) + self.time[:, :t]
        return self.heads(masked_pool(self.transformer(x, valid), valid))


class StreamingStudent(nn.Module):
    def __init__(self, config: StudentConfig):
        super().__init__()
        self.config = config
        self.frame_encoder = FrameEncoder(config)
        self.temporal = TemporalHead(config)

    @property
    def heads(self):
        return self.temporal.heads

    def forward(self, masks: torch.Tensor, valid: torch.Tensor) -> dict[str, torch.Tensor]:
        """masks (B, T, H, W) in [0, 1], valid (B, T)."""
        b, t, h, w = masks.shape
        frames = frame_encoder_input(self.config, masks, valid).reshape(b * t, -1, h, w)
        keep = valid.reshape(-1) > 0  # unobserved frames are never encoded (their embedding is zeroed anyway)
        encoded = self.frame_encoder(frames[keep])
        emb = encoded.new_zeros(b * t, encoded.shape[-1]).index_copy(0, keep.nonzero()[:, 0], encoded)
        return self.temporal(emb.reshape(b, t, -1), valid)


class LocalMHRA(nn.Module):
    """UniFormer local block: dynamic position encoding, local relation aggregator (depthwise 3D
    conv between pointwise convs), then a pointwise-conv MLP."""

    def __init__(self, dim: int, dropout: float):
        super().__init__()
        self.pos = nn.Conv3d(dim, dim, 3, padding=1, groups=dim)
        self.norm1 = nn.BatchNorm3d(dim)
        self.aggregate = nn.Sequential(nn.Conv3d(dim, dim, 1), nn.Conv3d(dim, dim, (3, 5, 5), padding=(1, 2, 2),
                                                                         groups=dim), nn.Conv3d(dim, dim, 1))
        self.norm2 = nn.BatchNorm3d(dim)
        self.mlp = nn.Sequential(nn.Conv3d(dim, 4 * dim, 1), nn.GELU(), nn.Dropout(dropout), nn.Conv3d(4 * dim, dim, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.pos(x)
        x = x + self.aggregate(self.norm1(x))
        return x + self.mlp(self.norm2(x))


class GlobalMHRA(nn.Module):
    """UniFormer global block: dynamic position encoding then self-attention over all tokens."""

    def __init__(self, dim: int, heads: int, dropout: float):
        super().__init__()
        self.pos = nn.Conv3d(dim, dim, 3, padding=1, groups=dim)
        self.transformer = Transformer(dim, 1, heads, dropout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.pos(x)
        b, c, t, h, w = x.shape
        tokens = self.transformer(x.flatten(2).transpose(1, 2))
        return tokens.transpose(1, 2).reshape(b, c, t, h, w)


class UniFormerStudent(nn.Module):
    def __init__(self, config: StudentConfig):
        super().__init__()
        self.config = c = config
        n = len(c.dims)
        # The stem quarters the image and each later stage halves it: a smaller input leaves no pixel
        # (a torch error in the first forward pass, after the data loaded).
        if min(c.input_size) < 4 * 2 ** (n - 1):
            raise ValueError(f"input size {c.input_size} is too small for {n} stages: the uniformer student needs "
                             f"at least {4 * 2 ** (n - 1)} pixels a side")
        stages, cin = [], 1
        for i, (dim, depth) in enumerate(zip(c.dims, c.depths)):
            # Stem: 4x spatial and 2x temporal downsampling; later stages halve space only.
            down = nn.Conv3d(cin, dim, (3, 4, 4), stride=(2, 4, 4), padding=(1, 0, 0)) if i == 0 else \
                nn.Conv3d(cin, dim, (1, 2, 2), stride=(1, 2, 2))
            blocks = [GlobalMHRA(dim, max(1, dim // 64), c.dropout) if i >= n - c.global_stages
                      else LocalMHRA(dim, c.dropout) for _ in range(depth)]
            stages.append(nn.Sequential(down, *blocks))
            cin = dim
        self.stages = nn.Sequential(*stages)
        self.norm = nn.LayerNorm(cin)
        self.heads = Heads(2 * cin, cin, c.z_dim)

    def forward(self, masks: torch.Tensor, valid: torch.Tensor) -> dict[str, torch.Tensor]:
        """masks (B, 25, H, W) in [0, 1], valid (B, 25); fewer frames are zero-padded to 25."""
        if masks.shape[1] < FRAME_COUNT:
            pad = FRAME_COUNT - masks.shape[1]
            masks, valid = F.pad(masks, (0, 0, 0, 0, 0, pad)), F.pad(valid, (0, pad))
        x = (masks * valid[:, :, None, None]).unsqueeze(1)
        x = self.stages(x).flatten(2).transpose(1, 2)
        return self.heads(masked_pool(self.norm(x)))


def build_student(config: StudentConfig) -> nn.Module:
    return StreamingStudent(config) if config.kind == "streaming" else UniFormerStudent(config)
