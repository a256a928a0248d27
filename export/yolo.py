"""A compact YOLOv8 detector (n and s) in plain torch.

The module tree mirrors the published YOLOv8 layout (a flat ``model`` Sequential-like list of 23
layers: Conv/C2f/SPPF backbone, PAN neck, anchor-free decoupled ``Detect`` head with DFL), so
state-dict keys (``model.0.conv.weight`` ... ``model.22.dfl.conv.weight``) and parameter counts
are those of the reference implementation and converted weights load with ``strict=True``.

Output in eval mode: ``[B, 4 + nc, N]``, rows cx, cy, w, h in input pixels then per-class
sigmoid scores, N = sum over strides 8/16/32 of (H/s)·(W/s) anchors. In train mode: the raw
per-level maps ``[B, 4·reg_max + nc, H/s, W/s]`` the loss consumes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

#: Width/depth multipliers of the published scales.
SCALES = {"n": (0.33, 0.25, 1024), "s": (0.33, 0.50, 1024), "m": (0.67, 0.75, 768)}
STRIDES = (8, 16, 32)
REG_MAX = 16


def make_divisible(x: float, divisor: int = 8) -> int:
    return int(math.ceil(x / divisor) * divisor)


class Conv(nn.Module):
    """Conv2d (no bias) → BatchNorm → SiLU, 'same' padding."""

    def __init__(self, c1: int, c2: int, k: int = 1, s: int = 1, g: int = 1):
        super().__init__()
        self.conv = nn.Conv2d(c1, c2, k, s, k // 2, groups=g, bias=False)
        self.bn = nn.BatchNorm2d(c2, eps=1e-3, momentum=0.03)
        self.act = nn.SiLU(inplace=True)

    def forward(self, x):
        return self.act(self.bn(self.conv(x)))


class Bottleneck(nn.Module):
    """Two 3x3 convs with an optional residual."""

    def __init__(self, c1: int, c2: int, shortcut: bool = True, e: float = 1.0):
        super().__init__()
        c_ = int(c2 * e)
        self.cv1 = Conv(c1, c_, 3)
        self.cv2 = Conv(c_, c2, 3)
        self.add = shortcut and c1 == c2

    def forward(self, x):
        y = self.cv2(self.cv1(x))
        return x + y if self.add else y


class C2f(nn.Module):
    """CSP block with two halves; every bottleneck output is kept and concatenated."""

    def __init__(self, c1: int, c2: int, n: int = 1, shortcut: bool = False, e: float = 0.5):
        super().__init__()
        self.c = int(c2 * e)
        self.cv1 = Conv(c1, 2 * self.c, 1)
        self.cv2 = Conv((2 + n) * self.c, c2, 1)
        self.m = nn.ModuleList(Bottleneck(self.c, self.c, shortcut, e=1.0) for _ in range(n))

    def forward(self, x):
        y = list(self.cv1(x).chunk(2, 1))
        for m in self.m:
            y.append(m(y[-1]))
        return self.cv2(torch.cat(y, 1))


class SPPF(nn.Module):
    """Spatial pyramid pooling (fast): three chained 5x5 max-pools."""

    def __init__(self, c1: int, c2: int, k: int = 5):
        super().__init__()
        c_ = c1 // 2
        self.cv1 = Conv(c1, c_, 1)
        self.cv2 = Conv(c_ * 4, c2, 1)
        self.m = nn.MaxPool2d(k, 1, k // 2)

    def forward(self, x):
        y = [self.cv1(x)]
        for _ in range(3):
            y.append(self.m(y[-1]))
        return self.cv2(torch.cat(y, 1))


class Upsample(nn.Upsample):
    def __init__(self):
        super().__init__(scale_factor=2.0, mode="nearest")


class Concat(nn.Module):
    """Concatenate the previous layer's output with saved outputs of earlier layers."""

    def __init__(self, sources: tuple[int, ...]):
        super().__init__()
        self.sources = sources

    def forward(self, xs: list[torch.Tensor]):
        return torch.cat(xs, 1)


class DFL(nn.Module):
    """Distribution focal loss integral: expected value of a softmax over ``reg_max`` bins (fixed 1x1 conv)."""

    def __init__(self, c1: int = REG_MAX):
        super().__init__()
        self.conv = nn.Conv2d(c1, 1, 1, bias=False).requires_grad_(False)
        self.conv.weight.data[:] = torch.arange(c1, dtype=torch.float32).view(1, c1, 1, 1)
        self.c1 = c1

    def forward(self, x):
        b, _, a = x.shape  # [B, 4*c1, A]
        return self.conv(x.view(b, 4, self.c1, a).transpose(2, 1).softmax(1)).view(b, 4, a)


def make_anchors(shapes: list[tuple[int, int]], strides, dtype, device, offset: float = 0.5):
    """Anchor centres in grid units per level, concatenated, and the matching stride column: ([A,2], [A,1])."""
    points, stride_col = [], []
    for (h, w), s in zip(shapes, strides, strict=True):
        sy, sx = torch.meshgrid(torch.arange(h, device=device, dtype=dtype) + offset,
                                torch.arange(w, device=device, dtype=dtype) + offset, indexing="ij")
        points.append(torch.stack((sx, sy), -1).view(-1, 2))
        stride_col.append(torch.full((h * w, 1), float(s), dtype=dtype, device=device))
    return torch.cat(points), torch.cat(stride_col)


def dist2bbox(distance, anchor_points, xywh: bool = True, dim: int = -1):
    """(left, top, right, bottom) distances from anchor points → boxes (cx,cy,w,h or x0,y0,x1,y1)."""
    lt, rb = distance.chunk(2, dim)
    x1y1 = anchor_points - lt
    x2y2 = anchor_points + rb
    if xywh:
        return torch.cat(((x1y1 + x2y2) / 2, x2y2 - x1y1), dim)
    return torch.cat((x1y1, x2y2), dim)


def bbox2dist(anchor_points, bbox, reg_max: int):
    """x0,y0,x1,y1 boxes → (l, t, r, b) distances, clamped to the DFL range [0, reg_max - 1 - eps]."""
    x1y1, x2y2 = bbox.chunk(2, -1)
    return torch.cat((anchor_points - x1y1, x2y2 - anchor_points), -1).clamp_(0, reg_max - 1 - 0.01)


class Detect(nn.Module):
    """Anchor-free decoupled head: per level a box branch (4·reg_max DFL logits) and a class branch."""

    def __init__(self, nc: int, ch: tuple[int, ...], strides=STRIDES, reg_max: int = REG_MAX):
        super().__init__()
        self.nc = nc
        self.nl = len(ch)
        self.reg_max = reg_max
        self.no = nc + 4 * reg_max
        self.register_buffer("stride", torch.tensor(strides, dtype=torch.float32), persistent=False)
        c2 = max(16, ch[0] // 4, reg_max * 4)
        c3 = max(ch[0], min(nc, 100))
        self.cv2 = nn.ModuleList(nn.Sequential(Conv(x, c2, 3), Conv(c2, c2, 3), nn.Conv2d(c2, 4 * reg_max, 1))
                                 for x in ch)
        self.cv3 = nn.ModuleList(nn.Sequential(Conv(x, c3, 3), Conv(c3, c3, 3), nn.Conv2d(c3, nc, 1)) for x in ch)
        self.dfl = DFL(reg_max)

    def bias_init(self, imgsz: int = 640) -> None:
        """Prior: box logits 1.0, class logits for ~5 objects per 640² image per level."""
        for a, b, s in zip(self.cv2, self.cv3, self.stride.tolist(), strict=True):
            a[-1].bias.data[:] = 1.0
            b[-1].bias.data[: self.nc] = math.log(5 / self.nc / (imgsz / s) ** 2)

    def forward(self, xs: list[torch.Tensor]):
        feats = [torch.cat((self.cv2[i](x), self.cv3[i](x)), 1) for i, x in enumerate(xs)]
        if self.training:
            return feats
        return self.decode(feats)

    def decode(self, feats: list[torch.Tensor]) -> torch.Tensor:
        """Raw level maps → [B, 4+nc, A]: cx, cy, w, h in input pixels, then sigmoid class scores."""
        b = feats[0].shape[0]
        shapes = [(f.shape[2], f.shape[3]) for f in feats]
        anchors, strides = make_anchors(shapes, self.stride.tolist(), feats[0].dtype, feats[0].device)
        x = torch.cat([f.view(b, self.no, -1) for f in feats], 2)
        box, cls = x.split((4 * self.reg_max, self.nc), 1)
        dbox = dist2bbox(self.dfl(box), anchors.transpose(0, 1).unsqueeze(0), xywh=True, dim=1)
        return torch.cat((dbox * strides.transpose(0, 1), cls.sigmoid()), 1)


@dataclass
class YoloSpec:
    """Which model: scale ('n' or 's') and number of classes."""

    scale: str = "n"
    nc: int = 3


class YOLOv8(nn.Module):
    """YOLOv8 detection model. ``forward(images [B,3,H,W] RGB 0..1)``; H and W multiples of 32."""

    def __init__(self, nc: int = 3, scale: str = "n", names: dict[int, str] | None = None):
        super().__init__()
        if scale not in SCALES:
            raise ValueError(f"unknown YOLOv8 scale {scale!r}; expected one of {sorted(SCALES)}")
        if nc < 1:
            raise ValueError(f"nc must be >= 1, got {nc}")
        depth, width, max_ch = SCALES[scale]
        self.scale, self.nc = scale, nc
        self.names = dict(names) if names else {i: f"class{i}" for i in range(nc)}
        if len(self.names) != nc:
            raise ValueError(f"{len(self.names)} class names for nc={nc}")

        def c(ch: int) -> int:
            return make_divisible(min(ch, max_ch) * width, 8)

        def n(k: int) -> int:
            return max(round(k * depth), 1)

        layers: list[nn.Module] = [
            Conv(3, c(64), 3, 2),                       # 0  P1/2
            Conv(c(64), c(128), 3, 2),                  # 1  P2/4
            C2f(c(128), c(128), n(3), True),            # 2
            Conv(c(128), c(256), 3, 2),                 # 3  P3/8
            C2f(c(256), c(256), n(6), True),            # 4
            Conv(c(256), c(512), 3, 2),                 # 5  P4/16
            C2f(c(512), c(512), n(6), True),            # 6
            Conv(c(512), c(1024), 3, 2),                # 7  P5/32
            C2f(c(1024), c(1024), n(3), True),          # 8
            SPPF(c(1024), c(1024), 5),                  # 9
            Upsample(),                                 # 10
            Concat((-1, 6)),                            # 11
            C2f(c(1024) + c(512), c(512), n(3)),        # 12
            Upsample(),                                 # 13
            Concat((-1, 4)),                            # 14
            C2f(c(512) + c(256), c(256), n(3)),         # 15 P3 out
            Conv(c(256), c(256), 3, 2),                 # 16
            Concat((-1, 12)),                           # 17
            C2f(c(256) + c(512), c(512), n(3)),         # 18 P4 out
            Conv(c(512), c(512), 3, 2),                 # 19
            Concat((-1, 9)),                            # 20
            C2f(c(512) + c(1024), c(1024), n(3)),       # 21 P5 out
            Detect(nc, (c(256), c(512), c(1024))),      # 22
        ]
        self.model = nn.ModuleList(layers)
        self._save = {4, 6, 9, 12, 15, 18, 21}
        self.model[-1].bias_init()

    @property
    def stride(self) -> torch.Tensor:
        return self.model[-1].stride

    def forward(self, x):
        saved: dict[int, torch.Tensor] = {}
        for i, m in enumerate(self.model):
            if isinstance(m, Concat):
                x = m([x if j == -1 else saved[j] for j in m.sources])
            elif isinstance(m, Detect):
                x = m([saved[15], saved[18], saved[21]])
            else:
                x = m(x)
            if i in self._save:
                saved[i] = x
        return x


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
