"""Building blocks shared by teacher and students: a mask-aware transformer (plain ops, so it
exports to ONNX), the projector and the prediction heads, and the losses of SPEC 9."""
from __future__ import annotations

import functools
import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ad_estimator.metrics import family_ranges
from ad_sim.materials import FAMILIES, PARAMETER_NAMES, normalise

NUM_CLASSES = len(FAMILIES)
NUM_PARAMS = len(PARAMETER_NAMES)
NLL_WEIGHT = 0.05  # a small weight on the uncertainty head's NLL (beside CE and RegL1)


def family_scales() -> np.ndarray:
    """(families, parameters) factors from the heads' parameter space (normalised over the union
    ranges, one head for all families) to each family's own normalised range, in which SPEC 8
    defines RegL1: plasticine's E and nu span half the union range, so their errors count double."""
    out = np.ones((len(FAMILIES), len(PARAMETER_NAMES)), np.float32)
    for f, ranges in enumerate(family_ranges().values()):  # in FAMILIES order
        for name, (lo, hi, _) in ranges.items():
            out[f, PARAMETER_NAMES.index(name)] = 1.0 / (normalise(name, hi) - normalise(name, lo))
    return out


@functools.lru_cache(maxsize=None)
def _family_scales_on(device: torch.device) -> torch.Tensor:
    """family_scales() as a tensor on `device`, made once per device (not copied every step)."""
    return torch.from_numpy(family_scales()).to(device)


class Attention(nn.Module):
    def __init__(self, dim: int, heads: int):
        super().__init__()
        if dim % heads:
            raise ValueError(f"width {dim} is not divisible by {heads} heads")
        self.heads, self.scale = heads, 1.0 / math.sqrt(dim // heads)
        self.qkv = nn.Linear(dim, 3 * dim)
        self.out = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, key_bias: torch.Tensor | None = None) -> torch.Tensor:
        b, n, d = x.shape
        q, k, v = self.qkv(x).reshape(b, n, 3, self.heads, d // self.heads).permute(2, 0, 3, 1, 4).unbind(0)
        scores = (q @ k.transpose(-2, -1)) * self.scale
        if key_bias is not None:  # (B, N): 0 for valid keys, large negative for padding
            scores = scores + key_bias[:, None, None, :]
        attn = scores.softmax(dim=-1)
        return self.out((attn @ v).transpose(1, 2).reshape(b, n, d))


class Block(nn.Module):
    """Pre-norm transformer block."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float = 4.0, dropout: float = 0.0):
        super().__init__()
        self.norm1, self.norm2 = nn.LayerNorm(dim), nn.LayerNorm(dim)
        self.attn = Attention(dim, heads)
        hidden = int(dim * mlp_ratio)
        self.mlp = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Dropout(dropout), nn.Linear(hidden, dim))

    def forward(self, x: torch.Tensor, key_bias: torch.Tensor | None = None) -> torch.Tensor:
        x = x + self.attn(self.norm1(x), key_bias)
        return x + self.mlp(self.norm2(x))


class Transformer(nn.Module):
    def __init__(self, dim: int, depth: int, heads: int, dropout: float = 0.0):
        super().__init__()
        self.blocks = nn.ModuleList(Block(dim, heads, dropout=dropout) for _ in range(depth))
        self.norm = nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        key_bias = None if valid is None else (1.0 - valid) * -1e4
        for block in self.blocks:
            x = block(x, key_bias)
        return self.norm(x)


def masked_pool(x: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
    """(B, N, D) -> (B, 2D): mean and max over valid tokens."""
    if valid is None:
        return torch.cat([x.mean(1), x.amax(1)], dim=-1)
    w = valid.unsqueeze(-1)
    mean = (x * w).sum(1) / w.sum(1).clamp(min=1.0)
    mx = (x + (1.0 - w) * -1e4).amax(1)
    return torch.cat([mean, mx], dim=-1)


class Predictor(nn.Module):
    """z -> class logits, normalised parameters (sigmoid, in [0, 1]) and their log-variance.
    Teacher and student share this shape, so a student can reuse the teacher's predictor."""

    def __init__(self, z_dim: int):
        super().__init__()
        self.hidden = nn.Sequential(nn.GELU(), nn.Linear(z_dim, z_dim), nn.GELU())
        self.cls = nn.Linear(z_dim, NUM_CLASSES)
        self.params = nn.Linear(z_dim, NUM_PARAMS)
        self.logvar = nn.Linear(z_dim, NUM_PARAMS)

    def forward(self, z: torch.Tensor) -> dict[str, torch.Tensor]:
        h = self.hidden(z)
        return {"z": z, "logits": self.cls(h), "params": torch.sigmoid(self.params(h)),
                "params_logvar": self.logvar(h).clamp(-12.0, 4.0)}


class Heads(nn.Module):
    """Pooled feature -> projector z (the aligned representation) -> predictor."""

    def __init__(self, in_dim: int, hidden: int, z_dim: int):
        super().__init__()
        self.projector = nn.Sequential(nn.LayerNorm(in_dim), nn.Linear(in_dim, hidden), nn.GELU(),
                                       nn.Linear(hidden, z_dim))
        self.predictor = Predictor(z_dim)

    def forward(self, pooled: torch.Tensor) -> dict[str, torch.Tensor]:
        return self.predictor(self.projector(pooled))


def masked_regl1(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """SPEC 8's RegL1: mean |pred - target| over each sample's valid (sampled) parameters, measured
    in its true family's own normalised ranges (pred and target are in the heads' union-normalised
    space), then over the batch. The same figure as ad_estimator.metrics.regl1."""
    scale = _family_scales_on(pred.device)[labels]
    per = (torch.abs(pred - target) * scale * mask).sum(1) / mask.sum(1).clamp(min=1.0)
    return per.mean()


def uncertainty_nll(out: dict, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Gaussian NLL of the log-variance head around the (detached) prediction, so it learns the
    error scale without changing what the parameter head learns."""
    err2 = (out["params"].detach() - target) ** 2
    nll = 0.5 * (err2 * torch.exp(-out["params_logvar"]) + out["params_logvar"])
    return ((nll * mask).sum(1) / mask.sum(1).clamp(min=1.0)).mean()


def task_loss(out: dict, labels: torch.Tensor, target: torch.Tensor, mask: torch.Tensor,
              regl1_weight: float = 1.0, nll_weight: float = NLL_WEIGHT, ce_weight: float = 1.0
              ) -> tuple[torch.Tensor, dict]:
    ce = F.cross_entropy(out["logits"], labels)
    reg = masked_regl1(out["params"], target, mask, labels)
    nll = uncertainty_nll(out, target, mask)
    loss = ce_weight * ce + regl1_weight * reg + nll_weight * nll
    acc = (out["logits"].argmax(-1) == labels).float().mean()
    # score (CE + RegL1) selects the best checkpoint
    return loss, {"ce": ce.detach(), "regl1": reg.detach(), "nll": nll.detach(), "acc": acc,
                  "score": (ce + reg).detach()}


def align_loss(z_v: torch.Tensor, z_t: torch.Tensor, alpha: float) -> torch.Tensor:
    """1 - cos(z_V, z_T) + alpha * mean |z_V - z_T| (SPEC 9)."""
    cos = F.cosine_similarity(z_v, z_t, dim=-1)
    return (1.0 - cos).mean() + alpha * torch.abs(z_v - z_t).mean()
