"""The TDCM network in PyTorch, written from ../shared/reference/README.md.

Module and parameter names follow the official state dict exactly (`backbone_O.stage1.blocks.0.
mlp.fc1.weight`, `conv_score.2.bias`, ...), so `model.state_dict()` saved with `torch.save` is a
checkpoint that `posematch weights import` reads unchanged. The Rust network (`src/model`) is the
one we serve; `tests/trainer_fixture.rs` checks that both compute the same function.
"""

import math

import torch
import torch.nn.functional as F
from torch import nn

CHANNELS = 96
HIDDEN = 384
DECODER = 96
HEAD_HIDDEN = 12
TEMPLATE_GRID = 36

# ImageNet statistics: the input convention the official checkpoint was trained with and
# `posematch` feeds by default (RGB in [0, 1], then (v - mean) / std).
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class LayerNorm2d(nn.Module):
    """LayerNorm over the channels of an NCHW map (eps 1e-6, biased variance, affine)."""

    def __init__(self, channels: int, eps: float = 1e-6):
        super().__init__()
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x.permute(0, 2, 3, 1)
        x = F.layer_norm(x, (x.shape[-1],), self.weight, self.bias, self.eps)
        return x.permute(0, 3, 1, 2)


class GlobalResponseNorm(nn.Module):
    """ConvNeXt-V2 GRN on NHWC: G = L2 norm over all positions, N = G / (mean_c G + 1e-6),
    z + bias + weight * z * N."""

    def __init__(self, channels: int):
        super().__init__()
        self.weight = nn.Parameter(torch.zeros(channels))
        self.bias = nn.Parameter(torch.zeros(channels))

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        # The norm in float32 even under autocast: a sum of squares over a whole map.
        g = torch.linalg.vector_norm(z.float(), ord=2, dim=(1, 2), keepdim=True)
        n = g / (g.mean(dim=-1, keepdim=True) + 1e-6)
        return z + self.bias + self.weight * z * n.to(z.dtype)


class Mlp(nn.Module):
    def __init__(self):
        super().__init__()
        self.fc1 = nn.Linear(CHANNELS, HIDDEN)
        self.grn = GlobalResponseNorm(HIDDEN)
        self.fc2 = nn.Linear(HIDDEN, CHANNELS)

    def forward(self, x):
        x = F.gelu(self.fc1(x))  # the exact erf form
        return self.fc2(self.grn(x))


class Block(nn.Module):
    """ConvNeXt-V2 block without downsampling, layer-scale or drop-path."""

    def __init__(self):
        super().__init__()
        self.conv_dw = nn.Conv2d(CHANNELS, CHANNELS, 7, padding=3, groups=CHANNELS)
        self.norm = nn.LayerNorm(CHANNELS, eps=1e-6)
        self.mlp = Mlp()

    def forward(self, x):
        y = self.conv_dw(x).permute(0, 2, 3, 1)
        y = self.mlp(self.norm(y))
        return x + y.permute(0, 3, 1, 2)


class Stage(nn.Module):
    def __init__(self):
        super().__init__()
        self.blocks = nn.Sequential(Block(), Block(), Block())

    def forward(self, x):
        return self.blocks(x)


class Backbone(nn.Module):
    """Stem (4x4 stride-4 conv + LayerNorm) and stage 1 of ConvNeXt-V2 tiny, then BatchNorm."""

    def __init__(self):
        super().__init__()
        self.stem = nn.Sequential(nn.Conv2d(3, CHANNELS, 4, stride=4), LayerNorm2d(CHANNELS))
        self.stage1 = Stage()
        self.norm = nn.BatchNorm2d(CHANNELS)

    def forward(self, x):
        return self.norm(self.stage1(self.stem(x)))


def head() -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(DECODER // 4, HEAD_HIDDEN, 3, padding=1),
        nn.ReLU(),
        nn.Conv2d(HEAD_HIDDEN, 1, 1),
    )


def depthwise_correlation(features: torch.Tensor, kernels: torch.Tensor) -> torch.Tensor:
    """Sample i's channel c correlated with sample i's kernel c; zero padding keeps the size."""
    b, c, h, w = features.shape
    k = kernels.shape[-1]
    out = F.conv2d(
        features.reshape(1, b * c, h, w),
        kernels.reshape(b * c, 1, k, k),
        padding=k // 2,
        groups=b * c,
    )
    return out.reshape(b, c, h, w)


class Tdcm(nn.Module):
    def __init__(self):
        super().__init__()
        self.backbone_T = Backbone()
        self.backbone_O = Backbone()
        self.pointwise_conv = nn.Conv2d(CHANNELS, CHANNELS, 3, padding=1)
        self.conv1 = nn.Conv2d(CHANNELS, 2 * DECODER, 3, padding=1)
        self.bn1 = nn.BatchNorm2d(2 * DECODER)
        self.conv2 = nn.Conv2d(2 * DECODER // 4, DECODER, 3, padding=1)
        self.bn2 = nn.BatchNorm2d(DECODER)
        self.conv_score = head()
        self.conv_sign = head()
        self.conv_cos = head()
        self.conv_scale_x = head()
        self.conv_scale_y = head()
        initialise(self)

    def forward(self, templates: torch.Tensor, searches: torch.Tensor) -> torch.Tensor:
        """templates [B,3,36,36], searches [B,3,H,W] (normalised) -> [B,5,4*(H//4),4*(W//4)]:
        score, sign, cos, scale_x, scale_y with their output functions applied."""
        kernels = self.backbone_T(templates)
        features = self.backbone_O(searches)
        x = depthwise_correlation(features, kernels.to(features.dtype))
        x = self.pointwise_conv(x)
        x = F.relu(self.bn1(self.conv1(x)))
        x = F.pixel_shuffle(x, 2)
        x = F.relu(self.bn2(self.conv2(x)))
        x = F.pixel_shuffle(x, 2)
        score = torch.sigmoid(self.conv_score(x))
        sign = torch.sigmoid(self.conv_sign(x))
        cos = torch.tanh(self.conv_cos(x))
        scale_x = torch.sigmoid(self.conv_scale_x(x)) * 1.5 + 0.5
        scale_y = torch.sigmoid(self.conv_scale_y(x)) * 1.5 + 0.5
        return torch.cat([score, sign, cos, scale_x, scale_y], dim=1)


def initialise(model: nn.Module) -> None:
    """Random initialisation as timm's ConvNeXt: truncated normal (std 0.02) for convolutions
    and linears, zero biases; the score head's last bias at -log((1 - p) / p) with p = 0.01 so
    that the centre loss starts near its floor instead of at the all-pixels-positive guess."""
    for m in model.modules():
        if isinstance(m, (nn.Conv2d, nn.Linear)):
            nn.init.trunc_normal_(m.weight, std=0.02)
            nn.init.zeros_(m.bias)
    if isinstance(model, Tdcm):
        nn.init.constant_(model.conv_score[2].bias, -math.log((1 - 0.01) / 0.01))


def normalise(rgb01: torch.Tensor) -> torch.Tensor:
    """[B,3,H,W] RGB in [0, 1] -> the network's input (ImageNet mean/std)."""
    mean = torch.tensor(IMAGENET_MEAN, device=rgb01.device, dtype=rgb01.dtype).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, device=rgb01.device, dtype=rgb01.dtype).view(1, 3, 1, 1)
    return (rgb01 - mean) / std
