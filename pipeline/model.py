"""The TinyUNet student: a three-level U-Net (channels 24, 48, 96) whose mask head gives the deployed logits Z, plus
the training-only SDF (tanh) and skeleton heads of Stage II on the same decoded features."""

from __future__ import annotations

import copy
from typing import Any, Iterable, Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import nn

#: normalisation layers of :class:`TinyUNet` (``train.norm``); "batch" is the paper's
NORMS = ("batch", "group")
GROUP_CHANNELS = 8  # channels per GroupNorm group: 24/48/96 channels -> 3/6/12 groups
DEFAULT_BN_MOMENTUM = 0.1  # PyTorch's


def norm_layer(kind: str, channels: int, bn_momentum: float = DEFAULT_BN_MOMENTUM) -> nn.Module:
    """The normalisation after each 3x3 convolution: BatchNorm, or GroupNorm of :data:`GROUP_CHANNELS` per group."""
    if kind == "batch":
        return nn.BatchNorm2d(channels, momentum=bn_momentum)
    if kind == "group":
        groups = max(1, channels // GROUP_CHANNELS)
        while channels % groups:
            groups -= 1
        return nn.GroupNorm(groups, channels)
    raise ValueError(f"norm {kind!r}: expected one of {', '.join(NORMS)}")


def model_options(cfg: Mapping[str, Any]) -> dict:
    """TinyUNet keyword arguments from the ``train`` params."""
    return {"norm": str(cfg["norm"]), "bn_momentum": float(cfg["bn_momentum"])}


class ConvBNReLU(nn.Sequential):
    def __init__(self, cin: int, cout: int, norm: str = "batch", bn_momentum: float = DEFAULT_BN_MOMENTUM):
        super().__init__(nn.Conv2d(cin, cout, 3, padding=1, bias=False), norm_layer(norm, cout, bn_momentum),
                         nn.ReLU(inplace=True))


class DoubleConv(nn.Sequential):
    def __init__(self, cin: int, cout: int, **norm: Any):
        super().__init__(ConvBNReLU(cin, cout, **norm), ConvBNReLU(cout, cout, **norm))


class GeometryHeads(nn.Module):
    """Training-only SDF (tanh) and skeleton (logit) heads on the shared decoded features."""

    def __init__(self, features: int):
        super().__init__()
        self.sdf = nn.Conv2d(features, 1, 1)
        self.skeleton = nn.Conv2d(features, 1, 1)

    def forward(self, feats: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"sdf": torch.tanh(self.sdf(feats)), "skeleton": self.skeleton(feats)}


def _unet(m: nn.Module, x: torch.Tensor, sizes=None) -> torch.Tensor:
    """The decoded features of ``m``'s encoder-decoder; ``sizes``: the two upsampling sizes (default: the skips')."""
    e1 = m.enc1(x)
    e2 = m.enc2(F.max_pool2d(e1, 2))
    e3 = m.enc3(F.max_pool2d(e2, 2))
    s2, s1 = sizes or (e2.shape[-2:], e1.shape[-2:])
    d2 = F.interpolate(e3, size=s2, mode="bilinear", align_corners=False)
    d2 = m.dec2(torch.cat([d2, e2], dim=1))
    d1 = F.interpolate(d2, size=s1, mode="bilinear", align_corners=False)
    return m.dec1(torch.cat([d1, e1], dim=1))


class TinyUNet(nn.Module):
    # images are float in [0, 1], normalised inside the model so that exported models take the same input
    MEAN = 0.5
    STD = 0.25

    def __init__(self, in_channels: int = 3, channels: Sequence[int] = (24, 48, 96), norm: str = "batch",
                 bn_momentum: float = DEFAULT_BN_MOMENTUM):
        super().__init__()
        c1, c2, c3 = (int(c) for c in channels)
        # ``config`` rebuilds the deployed model (checkpoints, export): ``norm`` only where it is not the
        # paper's BatchNorm, so default checkpoints stay byte-identical; the momentum only acts in training
        self.config = {"in_channels": int(in_channels), "channels": [c1, c2, c3]}
        if norm != "batch":
            self.config["norm"] = str(norm)
        kw = {"norm": norm, "bn_momentum": float(bn_momentum)}
        self.enc1 = DoubleConv(in_channels, c1, **kw)
        self.enc2 = DoubleConv(c1, c2, **kw)
        self.enc3 = DoubleConv(c2, c3, **kw)
        self.dec2 = DoubleConv(c3 + c2, c2, **kw)
        self.dec1 = DoubleConv(c2 + c1, c1, **kw)
        self.mask_head = nn.Conv2d(c1, 1, 1)
        self.geometry_heads: GeometryHeads | None = None  # training only, Stage II

    def decode(self, x: torch.Tensor) -> torch.Tensor:
        return _unet(self, (x - self.MEAN) / self.STD)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Mask logits Z [B,1,H,W], the deployed output (eq:inference-mask thresholds sigmoid(Z))."""
        return self.mask_head(self.decode(x))

    def add_geometry_heads(self) -> "TinyUNet":
        """Create fresh SDF and skeleton heads (start of Stage II); the mask path is untouched."""
        ref = self.mask_head.weight
        self.geometry_heads = GeometryHeads(self.config["channels"][0]).to(device=ref.device, dtype=ref.dtype)
        return self

    def forward_train(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        feats = self.decode(x)
        out = {"mask": self.mask_head(feats)}
        if self.geometry_heads is not None:
            out.update(self.geometry_heads(feats))
        return out

    def mask_path_state_dict(self) -> dict[str, torch.Tensor]:
        """Weights of the deployed path only (no geometry heads)."""
        return {k: v for k, v in self.state_dict().items() if not k.startswith("geometry_heads.")}


def mask_path_model(model: TinyUNet) -> TinyUNet:
    """A float32 CPU copy of the deployed mask path (TinyUNet without the geometry heads), eval mode."""
    deployed = TinyUNet(**model.config)
    deployed.load_state_dict(model.mask_path_state_dict())
    return deployed.float().eval().requires_grad_(False)


class ExportMaskPath(nn.Module):
    """A TinyUNet's mask path for export and int8 inference (docs/decisions.md): the normalisation folded into the
    first conv, conv(W, pad_0((x - m) / s)) = conv(W / s, pad_m(x)) - (m / s) sum(W); sizes from the input's shape."""

    def __init__(self, unet: TinyUNet):
        super().__init__()
        src = copy.deepcopy(unet).float().eval()
        first: nn.Conv2d = src.enc1[0][0]
        folded = nn.Conv2d(first.in_channels, first.out_channels, first.kernel_size, padding=0, bias=True)
        with torch.no_grad():
            folded.weight.copy_(first.weight / unet.STD)
            bias = first.bias if first.bias is not None else torch.zeros(first.out_channels)
            folded.bias.copy_(bias - first.weight.sum(dim=(1, 2, 3)) * (unet.MEAN / unet.STD))
        src.enc1[0][0] = folded
        self.config = dict(unet.config)
        self.pad_value = float(unet.MEAN)
        ph, pw = first.padding
        self.padding = (int(pw), int(pw), int(ph), int(ph))
        self.enc1, self.enc2, self.enc3 = src.enc1, src.enc2, src.enc3
        self.dec2, self.dec1, self.mask_head = src.dec2, src.dec1, src.mask_head

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2], x.shape[-1]
        return self.mask_head(_unet(self, F.pad(x, self.padding, value=self.pad_value), ((h // 2, w // 2), (h, w))))


@torch.no_grad()
def recompute_bn_stats(model: nn.Module, batches: Iterable[torch.Tensor]) -> int:
    """Precise BN: every BatchNorm's running statistics become the plain average of the batch statistics over
    ``batches`` with the current weights; the number of batches used (0: nothing changed)."""
    bns = [m for m in model.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm) and m.track_running_stats]
    if not bns:
        return 0
    saved = [(m.momentum, m.num_batches_tracked.clone(), m.running_mean.clone(), m.running_var.clone())
             for m in bns]
    was_training = model.training
    for m in bns:
        m.reset_running_stats()
        m.momentum = None  # cumulative average: running = mean over the batches seen
    model.train()
    n = 0
    for n, x in enumerate(batches, 1):
        model(x)
    for m, (momentum, tracked, mean, var) in zip(bns, saved):
        m.momentum = momentum
        m.num_batches_tracked.copy_(tracked)
        if n == 0:
            m.running_mean.copy_(mean)
            m.running_var.copy_(var)
    model.train(was_training)
    return n


def count_parameters(model: nn.Module, deployed_only: bool = True) -> int:
    """Number of parameters; ``deployed_only`` excludes the training-only geometry heads."""
    return sum(p.numel() for n, p in model.named_parameters()
               if not (deployed_only and n.startswith("geometry_heads.")))


def count_flops(model: nn.Module, height: int = 384, width: int = 384) -> int:
    """FLOPs of one forward pass of the deployed path (torch's FlopCounterMode: a multiply-add is 2)."""
    from torch.utils.flop_counter import FlopCounterMode

    ref = next(model.parameters())
    x = torch.zeros(1, model.config["in_channels"], height, width, device=ref.device, dtype=ref.dtype)
    was_training = model.training
    model.eval()
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        model(x)
    model.train(was_training)
    return int(counter.get_total_flops())
