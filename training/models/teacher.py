"""Stage I teacher: a P4Transformer-style point-tube encoder over tracked-particle trajectories.

Because the 1024 particles are tracked, anchor neighbourhoods found once at t=0 (farthest point
sampling + kNN) stay valid for every frame: each anchor's neighbours form a point tube. A shared
point MLP (max-pooled over the neighbours) encodes each tube slice, a temporal convolution over a
window of frames turns slices into tube tokens, and a transformer mixes all tokens.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import torch
from torch import nn

from training.models.common import Heads, Transformer, masked_pool


@dataclass
class TeacherConfig:
    anchors: int = 64
    neighbours: int = 16
    point_width: int = 128
    temporal_kernel: int = 3
    temporal_stride: int = 2
    width: int = 256
    depth: int = 4
    heads: int = 8
    z_dim: int = 256
    dropout: float = 0.1
    # Scale of the rotation-free strain features. Checkpoints from before it was recorded used 1.0
    # (hence the default); the presets use 5.0 (stiff materials strain a few percent).
    strain_scale: float = 1.0

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TeacherConfig":
        """A checkpoint's config; a field this version lacks is a ValueError naming it (not a TypeError)."""
        if unknown := sorted(set(d) - {f.name for f in fields(cls)}):
            raise ValueError(f"unknown config field{'s' * (len(unknown) > 1)} {', '.join(map(repr, unknown))}")
        return cls(**d)


TEACHER_PRESETS = {
    "paper": TeacherConfig(strain_scale=5.0),
    "small": TeacherConfig(anchors=32, neighbours=8, point_width=64, temporal_stride=3, width=128, depth=2,
                           heads=4, z_dim=128, strain_scale=5.0),
    "tiny": TeacherConfig(anchors=16, neighbours=8, point_width=32, temporal_stride=4, width=32, depth=1, heads=2,
                          z_dim=32, dropout=0.0, strain_scale=5.0),
}


def farthest_point_sampling(points: torch.Tensor, k: int) -> torch.Tensor:
    """(B, N, 3) -> (B, k) indices; deterministic (starts from particle 0)."""
    b, n, _ = points.shape
    idx = torch.zeros(b, k, dtype=torch.long, device=points.device)
    dist = torch.full((b, n), float("inf"), device=points.device)
    current = torch.zeros(b, dtype=torch.long, device=points.device)
    batch = torch.arange(b, device=points.device)
    for i in range(k):
        idx[:, i] = current
        d = ((points - points[batch, current].unsqueeze(1)) ** 2).sum(-1)
        dist = torch.minimum(dist, d)
        current = dist.argmax(-1)
    return idx


STRAIN_FEATURES = 9 + 6 + 1
_UPPER = (0, 1, 2, 4, 5, 8)  # upper triangle of a row-major 3x3


@torch.autocast("cuda", enabled=False)
def strain_features(f: torch.Tensor, scale: float = 5.0) -> torch.Tensor:
    """(..., 9) row-major F -> (..., 16): F - I, then the rotation-free C - I (C = F^T F, upper
    triangle) and det F - 1, both multiplied by `scale`. Objects tumble, so F - I alone is dominated by
    rotation; C and det F carry the strain that the material parameters govern. Computed in
    float32 even under autocast."""
    f = f.float()
    m = f.reshape(*f.shape[:-1], 3, 3)
    eye = torch.eye(3, device=f.device, dtype=f.dtype)
    cauchy_green = m.transpose(-1, -2) @ m
    c = (cauchy_green - eye).flatten(-2)[..., _UPPER]
    det = (torch.linalg.det(m) - 1.0).unsqueeze(-1)
    return torch.cat([(f - eye.flatten()).clamp(-10.0, 10.0),
                      (scale * torch.cat([c, det], dim=-1)).clamp(-20.0, 20.0)], dim=-1)


def _gather(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """x (B, T, N, C), idx (B, ...) -> (B, T, ..., C)."""
    b, t, n, c = x.shape
    flat = idx.reshape(b, 1, -1, 1).expand(b, t, -1, c)
    return torch.gather(x, 2, flat).reshape(b, t, *idx.shape[1:], c)


class Teacher(nn.Module):
    """Input (B, T, N, 15): x y z, normalised displacement, F row-major. Output dict with z
    (B, z_dim), logits (B, 3), params (B, 4) in [0, 1], params_logvar (B, 4)."""

    def __init__(self, config: TeacherConfig):
        super().__init__()
        self.config = c = config
        self.point_mlp = nn.Sequential(nn.Linear(3 + 3 + STRAIN_FEATURES, c.point_width // 2), nn.GELU(),
                                       nn.Linear(c.point_width // 2, c.point_width), nn.GELU(),
                                       nn.Linear(c.point_width, c.point_width))
        self.temporal = nn.Conv1d(c.point_width, c.width, c.temporal_kernel, stride=c.temporal_stride,
                                  padding=c.temporal_kernel // 2)
        self.position = nn.Sequential(nn.Linear(4, c.width), nn.GELU(), nn.Linear(c.width, c.width))
        self.transformer = Transformer(c.width, c.depth, c.heads, c.dropout)
        self.heads = Heads(2 * c.width, c.width, c.z_dim)

    @torch.no_grad()
    def tubes(self, traj: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Anchor indices (B, A) and neighbour indices (B, A, k), both found at t=0."""
        c = self.config
        p0 = traj[:, 0, :, :3]
        anchors = farthest_point_sampling(p0, c.anchors)
        centres = torch.gather(p0, 1, anchors.unsqueeze(-1).expand(-1, -1, 3))
        neighbours = torch.cdist(centres, p0).topk(c.neighbours, dim=-1, largest=False).indices
        return anchors, neighbours

    def forward(self, traj: torch.Tensor, anchors: torch.Tensor | None = None,
                neighbours: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """anchors (B, A) and neighbours (B, A, k) may be given (precomputed by `tubes`)."""
        c = self.config
        b, t = traj.shape[:2]
        if anchors is None or neighbours is None:
            anchors, neighbours = self.tubes(traj)
        centre = _gather(traj[..., :3], anchors)  # (B, T, A, 3)
        nb = _gather(traj, neighbours)  # (B, T, A, k, 15)
        features = torch.cat([
            (nb[..., :3] - centre.unsqueeze(3)) * 10.0,  # tube-local geometry, ~unit scale
            nb[..., 3:6].clamp(-20.0, 20.0),
            strain_features(nb[..., 6:], c.strain_scale),
        ], dim=-1)
        slices = self.point_mlp(features).amax(dim=3)  # (B, T, A, C)
        a = slices.shape[2]
        tokens = self.temporal(slices.permute(0, 2, 3, 1).reshape(b * a, -1, t))  # (B*A, D, T')
        tp = tokens.shape[-1]
        tokens = tokens.reshape(b, a, -1, tp).permute(0, 3, 1, 2)  # (B, T', A, D)
        frames = torch.arange(tp, device=traj.device) * c.temporal_stride
        where = torch.cat([
            centre[:, frames] - 0.5,
            (frames.to(traj.dtype) / max(t - 1, 1)).reshape(1, tp, 1, 1).expand(b, tp, a, 1),
        ], dim=-1)
        tokens = (tokens + self.position(where)).reshape(b, tp * a, -1)
        return self.heads(masked_pool(self.transformer(tokens)))
