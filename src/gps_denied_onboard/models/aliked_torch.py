"""ALIKED keypoint + descriptor network in PyTorch (build-time only: used to export ONNX and in tests).

Written for this project from the paper (Zhao et al., "ALIKED: A Lighter Keypoint and Descriptor
Extraction Network via Deformable Transformation", IEEE TIM 2023) and the layer names and shapes of the
official state dicts, which load with ``strict=True``. The daemon never imports it; it runs the export.

Input: one RGB image ``(1, 3, H, W)`` in [0, 1], H and W multiples of 32. Output: keypoints, scores and
L2-normalised descriptors, through:
* encoder: two plain 3x3 conv blocks (full and 1/2 resolution), two residual blocks with deformable 3x3
  convs (1/8 and 1/32); BatchNorm + SELU;
* aggregation: each scale projected to ``dim/4`` channels, upsampled (bilinear, align_corners) and
  concatenated -> ``(1, dim, H, W)``, L2-normalised: the dense feature map;
* score head: a small conv stack + sigmoid -> ``(1, 1, H, W)``;
* DKD: NMS by max-pooling (radius 2), border removal, fixed top-k, soft-argmax refinement in a 5x5
  window (temperature 0.1), score = bilinear sample of the score map at the refined point;
* SDDH: per keypoint a 3x3 patch predicts M=16 sample offsets; features sampled there, projected (1x1
  conv + SELU) and aggregated by per-position matrices -> L2-normalised descriptor.

Deformable convolution (v2, no modulation mask, as the official configs) is written with
``grid_sample``, so it exports to ONNX opset >= 16 as ``GridSample`` without the opset-19 ``DeformConv``.
Traceable with dynamic H and W: sizes come from ``x.shape`` or ``torch._shape_as_tensor``, never from
``torch.arange(H)``, ``flatten``/``unflatten`` of spatial axes or Python ``max`` (the dynamic-size parity
test catches that).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import cast

import torch
import torch.nn.functional as F
from torch import nn

#: The encoder pools by 2, 4 and 4: the input height and width must be multiples of this.
SIZE_MULTIPLE = 32


@dataclass(frozen=True)
class AlikedConfig:
    """Channel widths of one ALIKED variant (from the official configs)."""

    c1: int
    c2: int
    c3: int
    c4: int
    dim: int  # descriptor dimension D
    kernel_size: int  # SDDH patch size K
    n_pos: int  # SDDH sample positions M


ALIKED_CONFIGS: dict[str, AlikedConfig] = {
    "t16": AlikedConfig(c1=8, c2=16, c3=32, c4=64, dim=64, kernel_size=3, n_pos=16),
    "n16": AlikedConfig(c1=16, c2=32, c3=64, c4=128, dim=128, kernel_size=3, n_pos=16),
}

NMS_RADIUS = 2
SOFTARGMAX_TEMPERATURE = 0.1


def _size_hw(x: torch.Tensor) -> torch.Tensor:
    """``(2,)`` int64 tensor ``[H, W]`` of a ``(..., H, W)`` tensor; traced as an ONNX ``Shape`` node."""
    return torch._shape_as_tensor(x)[-2:]


# ---------------------------------------------------------------------------------------------- blocks


def deform_conv2d_3x3(
    x: torch.Tensor, offset: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None = None
) -> torch.Tensor:
    """3x3 deformable convolution, stride 1, padding 1, dilation 1, one offset group, no mask.

    Same semantics as ``torchvision.ops.deform_conv2d``: tap ``k = 3*ky + kx`` of output pixel ``(y, x)``
    reads ``x`` bilinearly at ``(y + ky - 1 + dy_k, x + kx - 1 + dx_k)``, with zeros outside the image.

    Args:
        x: ``(B, C, H, W)`` input.
        offset: ``(B, 18, H, W)``, channels ``(dy_0, dx_0, dy_1, dx_1, ...)`` (torchvision layout).
        weight: ``(O, C, 3, 3)``.
        bias: ``(O,)`` or None.

    Returns:
        ``(B, O, H, W)``.
    """
    # Shape values read from x.shape are recorded by the tracer (dynamic in ONNX); unflatten/flatten and
    # arange compute sizes internally and would freeze the trace size, hence the explicit reshapes.
    batch, channels, rows, cols = x.shape
    size = _size_hw(x).to(x.dtype)
    height, width = size[0], size[1]
    # Pixel indices via cumsum over a row/column of the input: the tracer would freeze torch.arange(H).
    ys = (torch.ones_like(x[:1, :1, :, :1]).cumsum(2) - 1.0).view(1, 1, -1, 1)
    xs = (torch.ones_like(x[:1, :1, :1, :]).cumsum(3) - 1.0).view(1, 1, 1, -1)
    taps = torch.arange(9, dtype=x.dtype)
    tap_y = (torch.div(taps, 3, rounding_mode="floor") - 1).view(1, 9, 1, 1)
    tap_x = (taps % 3 - 1).view(1, 9, 1, 1)
    off = offset.reshape(batch, 9, 2, rows, cols)
    pos_y = ys + tap_y + off[:, :, 0]  # (B, 9, H, W) pixel rows
    pos_x = xs + tap_x + off[:, :, 1]
    # align_corners=True maps -1..1 onto pixel centres 0..W-1, the same convention as the pixel grid above;
    # zero padding reproduces torchvision's "zero outside the image" bilinear interpolation.
    grid = torch.stack((2.0 * pos_x / (width - 1) - 1.0, 2.0 * pos_y / (height - 1) - 1.0), dim=-1)
    sampled = F.grid_sample(
        x, grid.reshape(batch, -1, cols, 2), mode="bilinear", padding_mode="zeros", align_corners=True
    )  # (B, C, 9*H, W), one GridSample for all taps
    columns = sampled.reshape(batch, channels * 9, rows, cols)  # index c*9 + k
    return F.conv2d(columns, weight.flatten(1)[:, :, None, None], bias)


class DeformConv2d(nn.Module):
    """Deformable 3x3 conv whose offsets come from a plain 3x3 conv, clamped to a quarter of the map."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.offset_conv = nn.Conv2d(in_channels, 2 * 9, kernel_size=3, padding=1, bias=True)
        self.regular_conv = nn.Conv2d(in_channels, out_channels, kernel_size=3, padding=1, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, C_in, H, W)`` -> ``(B, C_out, H, W)``."""
        max_offset = _size_hw(x).max().to(x.dtype) / 4.0
        offset = torch.clamp(self.offset_conv(x), -max_offset, max_offset)
        return deform_conv2d_3x3(x, offset, self.regular_conv.weight, self.regular_conv.bias)


def _conv3x3(in_channels: int, out_channels: int, deformable: bool) -> nn.Module:
    if deformable:
        return DeformConv2d(in_channels, out_channels)
    return nn.Conv2d(in_channels, out_channels, kernel_size=3, padding=1, bias=False)


class ConvBlock(nn.Module):
    """Two (3x3 conv -> BatchNorm -> SELU)."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.conv1 = _conv3x3(in_channels, out_channels, deformable=False)
        self.bn1 = nn.BatchNorm2d(out_channels)
        self.conv2 = _conv3x3(out_channels, out_channels, deformable=False)
        self.bn2 = nn.BatchNorm2d(out_channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, C_in, H, W)`` -> ``(B, C_out, H, W)``."""
        x = F.selu(self.bn1(self.conv1(x)))
        return F.selu(self.bn2(self.conv2(x)))


class ResBlock(nn.Module):
    """Residual block: two 3x3 convs (plain or deformable) + BatchNorm, 1x1 conv shortcut, SELU."""

    def __init__(self, in_channels: int, out_channels: int, deformable: bool) -> None:
        super().__init__()
        self.conv1 = _conv3x3(in_channels, out_channels, deformable)
        self.bn1 = nn.BatchNorm2d(out_channels)
        self.conv2 = _conv3x3(out_channels, out_channels, deformable)
        self.bn2 = nn.BatchNorm2d(out_channels)
        self.downsample = nn.Conv2d(in_channels, out_channels, kernel_size=1, bias=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, C_in, H, W)`` -> ``(B, C_out, H, W)``."""
        out = F.selu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return F.selu(out + self.downsample(x))


# ------------------------------------------------------------------------------------------------- DKD


def _nms_keep_maxima(scores: torch.Tensor, radius: int) -> torch.Tensor:
    """Non-maximum suppression by max-pooling; suppressed pixels are set to 0.

    Two extra rounds recover maxima that were only hidden by a suppressed neighbour (as in DKD).
    ``scores``: ``(B, 1, H, W)`` -> same shape.
    """

    def pool(t: torch.Tensor) -> torch.Tensor:
        return F.max_pool2d(t, kernel_size=2 * radius + 1, stride=1, padding=radius)

    zeros = torch.zeros_like(scores)
    max_mask = scores == pool(scores)
    for _ in range(2):
        suppressed = pool(max_mask.float()) > 0
        supp_scores = torch.where(suppressed, zeros, scores)
        new_max = supp_scores == pool(supp_scores)
        max_mask = max_mask | (new_max & ~suppressed)
    return torch.where(max_mask, scores, zeros)


def detect_keypoints(
    score_map: torch.Tensor, top_k: int, radius: int = NMS_RADIUS
) -> tuple[torch.Tensor, torch.Tensor]:
    """DKD in fixed top-k mode, for a batch of one.

    Args:
        score_map: ``(1, 1, H, W)`` scores in [0, 1].
        top_k: number of keypoints N (must be <= H*W).
        radius: NMS and soft-argmax radius in pixels.

    Returns:
        keypoints ``(N, 2)`` float pixel coordinates ``(x, y)``, refined to sub-pixel, in order of
        decreasing NMS score; scores ``(N,)``, the score map sampled bilinearly at the refined points.
    """
    nms = _nms_keep_maxima(score_map, radius)
    # Zero a border of `radius` pixels: the 5x5 refinement window would leave the map there.
    nms = F.pad(nms[:, :, radius:-radius, radius:-radius], (radius, radius, radius, radius))
    indices = torch.topk(nms.reshape(-1), top_k).indices  # (N,) into H*W, sorted by score
    size = _size_hw(score_map)
    width = size[1]
    kx = indices % width
    ky = torch.div(indices, width, rounding_mode="floor")

    # Soft-argmax over the (2r+1)^2 window of the raw score map (zero-padded like nn.Unfold would).
    win = 2 * radius + 1
    padded = F.pad(score_map, (radius, radius, radius, radius))
    tap = torch.arange(win * win)
    tap_dy = torch.div(tap, win, rounding_mode="floor")  # 0..2r, row-major window
    tap_dx = tap % win
    neighbours = (ky[:, None] + tap_dy) * (width + 2 * radius) + (kx[:, None] + tap_dx)  # (N, win^2)
    patch = padded.reshape(-1)[neighbours]  # (N, win^2)
    offsets_xy = torch.stack((tap_dx, tap_dy), dim=-1).to(score_map.dtype) - radius  # (win^2, 2)
    weights = torch.exp((patch - patch.max(dim=1, keepdim=True).values) / SOFTARGMAX_TEMPERATURE)
    residual = (weights @ offsets_xy) / weights.sum(dim=1, keepdim=True)  # (N, 2)
    keypoints = torch.stack((kx, ky), dim=-1).to(score_map.dtype) + residual

    wh_minus_1 = (size.flip(0) - 1).to(score_map.dtype)  # (W-1, H-1)
    grid = (2.0 * keypoints / wh_minus_1 - 1.0).view(1, 1, -1, 2)
    scores = F.grid_sample(score_map, grid, mode="bilinear", align_corners=True).reshape(-1)  # (N,)
    return keypoints, scores


# ------------------------------------------------------------------------------------------------ SDDH


class SDDH(nn.Module):
    """Sparse deformable descriptor head (state-dict name ``desc_head``)."""

    def __init__(self, dim: int, kernel_size: int, n_pos: int) -> None:
        super().__init__()
        self.kernel_size = kernel_size
        self.n_pos = n_pos
        self.offset_conv = nn.Sequential(
            nn.Conv2d(dim, 2 * n_pos, kernel_size=kernel_size, bias=True),
            nn.SELU(),
            nn.Conv2d(2 * n_pos, 2 * n_pos, kernel_size=1, bias=True),
        )
        self.sf_conv = nn.Conv2d(dim, dim, kernel_size=1, bias=False)
        # Filled from the state dict; (M, C, D) per-position aggregation matrices.
        self.agg_weights = nn.Parameter(torch.zeros(n_pos, dim, dim))

    def forward(self, feature_map: torch.Tensor, keypoints: torch.Tensor) -> torch.Tensor:
        """Descriptors at keypoints.

        Args:
            feature_map: ``(1, C, H, W)`` L2-normalised dense features.
            keypoints: ``(N, 2)`` pixel coordinates ``(x, y)``.

        Returns:
            ``(N, D)`` L2-normalised descriptors (D = C).
        """
        k = self.kernel_size
        size = _size_hw(feature_map)
        width = size[1]
        wh_minus_1 = (size.flip(0) - 1).to(feature_map.dtype)
        channels = feature_map.shape[1]

        # K x K patch whose top-left corner is floor(kpt) - K//2, clamped so that it stays inside the map
        # (the official clamp stops one pixel short of the right/bottom edge; kept for identical output).
        corner = keypoints.long() - k // 2
        corner = torch.minimum(corner.clamp(min=0), size.flip(0) - 1 - k)  # (N, 2) (x, y)
        tap = torch.arange(k * k)
        rows = corner[:, 1:2] + torch.div(tap, k, rounding_mode="floor")  # (N, K*K)
        cols = corner[:, 0:1] + tap % k
        flat = feature_map[0].reshape(channels, -1)  # (C, H*W), a view: no copy of the large map
        patches = flat[:, rows * width + cols]  # (C, N, K*K)
        patches = patches.permute(1, 0, 2).flatten(1)  # (N, C*K*K), matching conv weight layout

        conv_a, conv_b = cast(nn.Conv2d, self.offset_conv[0]), cast(nn.Conv2d, self.offset_conv[2])
        hidden = F.selu(F.linear(patches, conv_a.weight.flatten(1), conv_a.bias))
        offsets = F.linear(hidden, conv_b.weight.flatten(1), conv_b.bias)  # (N, 2M): M x-offsets, M y
        max_offset = size.max().to(feature_map.dtype) / 4.0
        offsets = torch.clamp(offsets, -max_offset, max_offset)
        offsets_xy = offsets.reshape(-1, 2, self.n_pos).transpose(1, 2)  # (N, M, 2)

        positions = keypoints[:, None, :] + offsets_xy  # (N, M, 2) pixels
        grid = (2.0 * positions / wh_minus_1 - 1.0)[None]  # (1, N, M, 2)
        sampled = F.grid_sample(feature_map, grid, mode="bilinear", align_corners=True)  # (1, C, N, M)
        sampled = F.selu(self.sf_conv(sampled))[0]  # (C, N, M)
        # descriptor[n] = sum_{m, c} sampled[c, n, m] * agg[m, c, :]
        stacked = sampled.permute(1, 2, 0).reshape(-1, self.n_pos * channels)  # (N, M*C)
        descriptors = stacked @ self.agg_weights.flatten(0, 1)  # (N, D)
        return F.normalize(descriptors, p=2.0, dim=1)


# ----------------------------------------------------------------------------------------------- model


class Aliked(nn.Module):
    """ALIKED extractor: image -> (keypoints, scores, descriptors), LightGlue-ONNX extractor layout.

    Parameter names follow the official state dicts so that they load with ``strict=True``.
    """

    def __init__(self, config: AlikedConfig, top_k: int = 1024) -> None:
        super().__init__()
        if top_k <= 0:
            raise ValueError(f"top_k must be positive (fixed top-k mode), got {top_k}")
        self.config = config
        self.top_k = top_k
        c = config
        self.block1 = ConvBlock(3, c.c1)
        self.block2 = ResBlock(c.c1, c.c2, deformable=False)
        self.block3 = ResBlock(c.c2, c.c3, deformable=True)
        self.block4 = ResBlock(c.c3, c.c4, deformable=True)
        quarter = c.dim // 4
        self.conv1 = nn.Conv2d(c.c1, quarter, kernel_size=1, bias=False)
        self.conv2 = nn.Conv2d(c.c2, quarter, kernel_size=1, bias=False)
        self.conv3 = nn.Conv2d(c.c3, quarter, kernel_size=1, bias=False)
        self.conv4 = nn.Conv2d(c.c4, quarter, kernel_size=1, bias=False)
        self.score_head = nn.Sequential(
            nn.Conv2d(c.dim, 8, kernel_size=1, bias=False),
            nn.SELU(),
            nn.Conv2d(8, 4, kernel_size=3, padding=1, bias=False),
            nn.SELU(),
            nn.Conv2d(4, 4, kernel_size=3, padding=1, bias=False),
            nn.SELU(),
            nn.Conv2d(4, 1, kernel_size=3, padding=1, bias=False),
        )
        self.desc_head = SDDH(c.dim, c.kernel_size, c.n_pos)

    def dense_maps(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(1, 3, H, W)`` -> feature map ``(1, D, H, W)`` (L2-normalised), score map ``(1, 1, H, W)``."""
        x1 = self.block1(image)  # (1, c1, H, W)
        x2 = self.block2(F.avg_pool2d(x1, 2))  # (1, c2, H/2, W/2)
        x3 = self.block3(F.avg_pool2d(x2, 4))  # (1, c3, H/8, W/8)
        x4 = self.block4(F.avg_pool2d(x3, 4))  # (1, c4, H/32, W/32)
        full = x1.shape[-2:]

        def up(t: torch.Tensor) -> torch.Tensor:
            # Size-based upsampling equals the official scale-factor upsampling when H, W % 32 == 0.
            return F.interpolate(t, size=full, mode="bilinear", align_corners=True)

        x1234 = torch.cat(
            [
                F.selu(self.conv1(x1)),
                up(F.selu(self.conv2(x2))),
                up(F.selu(self.conv3(x3))),
                up(F.selu(self.conv4(x4))),
            ],
            dim=1,
        )  # (1, D, H, W)
        score_map = torch.sigmoid(self.score_head(x1234))
        feature_map = F.normalize(x1234, p=2.0, dim=1)
        return feature_map, score_map

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Extract features.

        Args:
            image: ``(1, 3, H, W)`` float32 RGB in [0, 1]; H, W multiples of 32; ``H*W >= top_k``.

        Returns:
            keypoints ``(1, N, 2)`` float32 pixel ``(x, y)``; scores ``(1, N)``; descriptors ``(1, N, D)``
            L2-normalised; N = ``top_k``.
        """
        if not torch.jit.is_tracing():
            check_image_shape(tuple(image.shape), self.top_k)
        feature_map, score_map = self.dense_maps(image)
        keypoints, scores = detect_keypoints(score_map, self.top_k)
        descriptors = self.desc_head(feature_map, keypoints)
        return keypoints[None], scores[None], descriptors[None]


def check_image_shape(shape: tuple[int, ...], top_k: int) -> None:
    """Raise ``ValueError`` unless ``shape`` is ``(1, 3, H, W)`` with H, W multiples of 32, H*W >= top_k."""
    if len(shape) != 4 or shape[0] != 1 or shape[1] != 3:
        raise ValueError(f"ALIKED expects an image of shape (1, 3, H, W), got {shape}")
    height, width = shape[2], shape[3]
    if height % SIZE_MULTIPLE or width % SIZE_MULTIPLE:
        raise ValueError(
            f"ALIKED needs height and width that are multiples of {SIZE_MULTIPLE}, got {height}x{width}"
        )
    if height * width < top_k:
        raise ValueError(f"top_k={top_k} is more than the {height}x{width} pixels of the image")


def load_aliked(weights_path: str | Path, variant: str = "t16", top_k: int = 1024) -> Aliked:
    """Build the network for ``variant`` and load official weights with ``strict=True``, in eval mode.

    Raises:
        ValueError: unknown variant.
        RuntimeError: the state dict does not match the architecture (missing/unexpected/mis-shaped keys).
    """
    if variant not in ALIKED_CONFIGS:
        raise ValueError(f"unknown ALIKED variant {variant!r}; valid: {sorted(ALIKED_CONFIGS)}")
    model = Aliked(ALIKED_CONFIGS[variant], top_k=top_k)
    state = torch.load(Path(weights_path), map_location="cpu", weights_only=True)
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise RuntimeError(f"{weights_path}: not ALIKED-{variant} weights: {exc}") from exc
    return model.eval()
