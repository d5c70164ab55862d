"""A small PVNet-style fully convolutional network: object mask + unit vectors to K keypoints.

Sized for CPU training (about 0.5 M parameters): a strided encoder to 1/16 resolution and a
decoder with skip connections back to 1/2 of the input, where it predicts one mask logit and
2*K vector channels (x, y per keypoint, normalised to unit length).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

OUTPUT_STRIDE = 2  # the output grid is 1/2 of the network input


def _conv(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class _Down(nn.Module):
    """Strided conv then a residual 3x3 conv: halves the resolution."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.down = _conv(cin, cout, 2)
        self.conv = nn.Sequential(nn.Conv2d(cout, cout, 3, 1, 1, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x):
        x = self.down(x)
        return F.relu(x + self.conv(x))


class _Up(nn.Module):
    """Bilinear x2 upsampling, concatenation with the skip, one conv."""

    def __init__(self, cin: int, cskip: int, cout: int):
        super().__init__()
        self.conv = _conv(cin + cskip, cout)

    def forward(self, x, skip):
        x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
        return self.conv(torch.cat([x, skip], dim=1))


class PvnetNet(nn.Module):
    """Input (B, 3, H, W) RGB in [0, 1]; output (B, 1 + 2K, H/2, W/2): mask logit, unit vectors."""

    def __init__(self, num_keypoints: int = 9, width: int = 24):
        super().__init__()
        w = width
        self.num_keypoints = num_keypoints
        self.register_buffer("mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1))
        self.d1 = _Down(3, w)  # 1/2
        self.d2 = _Down(w, 2 * w)  # 1/4
        self.d3 = _Down(2 * w, 3 * w)  # 1/8
        self.d4 = _Down(3 * w, 4 * w)  # 1/16
        self.ctx = nn.Sequential(  # widen the receptive field at 1/16
            nn.Conv2d(4 * w, 4 * w, 3, 1, 2, dilation=2, bias=False), nn.BatchNorm2d(4 * w), nn.ReLU(inplace=True)
        )
        self.u3 = _Up(4 * w, 3 * w, 3 * w)
        self.u2 = _Up(3 * w, 2 * w, 2 * w)
        self.u1 = _Up(2 * w, w, w)
        self.head = nn.Conv2d(w, 1 + 2 * num_keypoints, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = (x - self.mean) / self.std
        s1 = self.d1(x)
        s2 = self.d2(s1)
        s3 = self.d3(s2)
        y = self.ctx(self.d4(s3))
        y = self.u1(self.u2(self.u3(y, s3), s2), s1)
        out = self.head(y)
        logit, vec = out[:, :1], out[:, 1:]
        b, _, h, w = vec.shape
        vec = vec.reshape(b, self.num_keypoints, 2, h, w)
        vec = vec / torch.sqrt((vec * vec).sum(dim=2, keepdim=True) + 1e-8)
        return torch.cat([logit, vec.reshape(b, 2 * self.num_keypoints, h, w)], dim=1)
