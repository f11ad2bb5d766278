"""TinyUNet student (paper: "Compact Student Distillation for Stable Silhouette Learning").

Architecture at a glance (channels (24, 48, 96), 384x384 input)::

    x [B,3,H,W] in [0,1] -> normalise
    enc1  ConvBNReLU(3->24),  ConvBNReLU(24->24)          H   x W
    enc2  maxpool, ConvBNReLU(24->48), ConvBNReLU(48->48)  H/2 x W/2
    enc3  maxpool, ConvBNReLU(48->96), ConvBNReLU(96->96)  H/4 x W/4
    dec2  bilinear x2, concat enc2, ConvBNReLU(144->48), ConvBNReLU(48->48)
    dec1  bilinear x2, concat enc1, ConvBNReLU(72->24),  ConvBNReLU(24->24)   -> decoded features F
    mask_head  Conv1x1(24->1)           -> Z (mask logits), P = sigmoid(Z)          [deployed]
    --- training only (Stage II; created by add_geometry_heads) ---
    geometry_heads.sdf       Conv1x1(24->1) + tanh -> D^S in [-1,1]
    geometry_heads.skeleton  Conv1x1(24->1)        -> Z^K (skeleton logits)

Normalisation (issue 17, item 4; the paper names BatchNorm only): ``norm="batch"`` (default, the
paper's ConvBNReLU) with ``bn_momentum`` for the running statistics (PyTorch's 0.1 by default), or
``norm="group"`` -- GroupNorm with :data:`GROUP_CHANNELS` channels per group, which has no batch or
running statistics, so training and evaluation normalise alike.  :func:`recompute_bn_stats` is
"precise BN": the running statistics re-estimated over a fixed set of batches with the current weights.

``forward(x)`` is the deployed path and returns mask logits only; :class:`ExportMaskPath` is the same
function in the form that is exported and quantised (normalisation folded into the first conv).  ``forward_train(x)`` returns a dict
with ``mask`` logits and, when the geometry heads exist, ``sdf`` and ``skeleton``.  The area term
(eq:predicted-area) uses P and has no head.
"""

from __future__ import annotations

import copy
from typing import Any, Iterable, Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import nn

#: normalisation layers of :class:`TinyUNet` (``train.norm``); "batch" is the paper's
NORMS = ("batch", "group")
#: channels per GroupNorm group (``norm="group"``): 24/48/96 channels -> 3/6/12 groups
GROUP_CHANNELS = 8
#: PyTorch's BatchNorm momentum, the default of ``train.bn_momentum``
DEFAULT_BN_MOMENTUM = 0.1


def norm_layer(kind: str, channels: int, bn_momentum: float = DEFAULT_BN_MOMENTUM) -> nn.Module:
    """The normalisation after each 3x3 convolution: ``BatchNorm2d(channels, momentum=bn_momentum)``
    for ``"batch"``; ``GroupNorm`` with :data:`GROUP_CHANNELS` channels per group for ``"group"`` (one
    group per channel below that width, never fewer than one group)."""
    if kind == "batch":
        return nn.BatchNorm2d(channels, momentum=bn_momentum)
    if kind == "group":
        groups = max(1, channels // GROUP_CHANNELS)
        while channels % groups:
            groups -= 1
        return nn.GroupNorm(groups, channels)
    raise ValueError(f"norm {kind!r}: expected one of {', '.join(NORMS)}")


def model_options(cfg: Mapping[str, Any]) -> dict:
    """TinyUNet keyword arguments from the ``train`` params: ``norm`` and ``bn_momentum``."""
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


class TinyUNet(nn.Module):
    # input normalisation: images are float in [0, 1]; centre and scale inside the model so that
    # exported models take the same input as the PyTorch one.
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

    # ---- shared trunk -------------------------------------------------------------------------
    def decode(self, x: torch.Tensor) -> torch.Tensor:
        x = (x - self.MEAN) / self.STD
        e1 = self.enc1(x)
        e2 = self.enc2(F.max_pool2d(e1, 2))
        e3 = self.enc3(F.max_pool2d(e2, 2))
        d2 = F.interpolate(e3, size=e2.shape[-2:], mode="bilinear", align_corners=False)
        d2 = self.dec2(torch.cat([d2, e2], dim=1))
        d1 = F.interpolate(d2, size=e1.shape[-2:], mode="bilinear", align_corners=False)
        return self.dec1(torch.cat([d1, e1], dim=1))

    # ---- deployed path ------------------------------------------------------------------------
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Mask logits Z [B,1,H,W] (the only output at inference, eq:inference-mask thresholds sigmoid(Z))."""
        return self.mask_head(self.decode(x))

    # ---- training-only ------------------------------------------------------------------------
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
    """The deployed mask path of a TinyUNet, rearranged for export and integer inference.

    Computes the same function as ``TinyUNet.forward`` (Z = f(x), eq:inference-mask), with two
    rearrangements that change no value beyond float round-off:

    * the input normalisation is folded into the first convolution::

          conv(W, pad_0((x - m) / s)) = conv(W / s, pad_m(x)) - (m / s) * sum(W)     per output channel

      (zero padding in normalised space is padding with m in image space).  The graph input is then
      the image itself, x = k / 255 for 8-bit images, which an int8 model represents exactly
      (scale 1/255, zero point 0); quantising the normalised input instead puts every pixel half a
      grey level off, which moved the validation IoU of a trained student by 0.0075.
    * the decoder's upsampling sizes are read from the input's shape (H // 2, H), which equals the
      skip tensors' sizes after the floor-dividing max-pools, so the exported graph takes the shape of
      the input only and no feature map is consumed by a Shape node (ONNX Runtime then keeps the
      quantised feature maps in int8).

    The training-only geometry heads are not part of it.  Built from a trained model by copying
    (the source module is not modified).
    """

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
        e1 = self.enc1(F.pad(x, self.padding, value=self.pad_value))
        e2 = self.enc2(F.max_pool2d(e1, 2))
        e3 = self.enc3(F.max_pool2d(e2, 2))
        d2 = F.interpolate(e3, size=(h // 2, w // 2), mode="bilinear", align_corners=False)
        d2 = self.dec2(torch.cat([d2, e2], dim=1))
        d1 = F.interpolate(d2, size=(h, w), mode="bilinear", align_corners=False)
        return self.mask_head(self.dec1(torch.cat([d1, e1], dim=1)))


@torch.no_grad()
def recompute_bn_stats(model: nn.Module, batches: Iterable[torch.Tensor]) -> int:
    """Precise BN: replace every BatchNorm's running mean/variance by the plain average of the batch
    statistics over ``batches`` (forward passes in training mode, no gradient, current weights).

    The EMA of training (``momentum`` 0.1) weights the last ~10 batches of 4 images, taken while the
    weights still move; this estimate weights every batch alike with the final weights.  Each BN
    layer's input is produced as in training (earlier layers normalise by batch statistics).
    ``num_batches_tracked`` and each layer's momentum are restored; the model's mode is restored.
    Returns the number of batches used (0: no BatchNorm layer or no batch -- nothing changed).
    """
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
    for x in batches:
        model(x)
        n += 1
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
    """FLOPs of one forward pass of the deployed path, counted from the graph by
    ``torch.utils.flop_counter.FlopCounterMode`` (a multiply-add counts as 2 FLOPs)."""
    from torch.utils.flop_counter import FlopCounterMode

    ref = next(model.parameters())
    x = torch.zeros(1, model.config["in_channels"], height, width, device=ref.device, dtype=ref.dtype)
    was_training = model.training
    model.eval()
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        model(x)
    model.train(was_training)
    return int(counter.get_total_flops())
