"""The TinyUNet student.

A three-level U-Net (widths ``train.channels``) whose mask head gives the deployed logits Z, plus the training-only
SDF (tanh) and skeleton heads of Stage II on the same decoded features.  Training-time capacity that folds away:
RepVGG's branches beside each 3x3 convolution (``train.expand_branches``; :func:`expand_branches`,
:func:`fold_branches`).
"""

from __future__ import annotations

import copy
from typing import Any, Iterable, Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import nn

from pipeline.params import PAPER

__all__ = ["NORMS", "model_options", "batch_norm_relu", "ConvBNReLU", "ExpandedConvBNReLU", "has_branches",
           "expand_branches", "fold_branches", "TinyUNet", "mask_path_model", "ExportMaskPath", "recompute_bn_stats",
           "count_parameters", "count_flops"]

#: normalisation layers of :class:`TinyUNet` (``train.norm``); the first, BatchNorm, is the paper's, and the one a
#: model ``config`` without a ``norm`` key means (checkpoints written before the option keep their bytes)
NORMS = ("batch", "group")
GROUP_CHANNELS = 8  # channels per GroupNorm group: 24/48/96 channels -> 3/6/12 groups


def norm_layer(kind: str, channels: int, bn_momentum: float) -> nn.Module:
    """Build the normalisation after each 3x3 convolution: BatchNorm, or GroupNorm of :data:`GROUP_CHANNELS` a group."""
    if kind == "batch":
        return nn.BatchNorm2d(channels, momentum=bn_momentum)
    if kind == "group":
        groups = max(1, channels // GROUP_CHANNELS)
        while channels % groups:
            groups -= 1
        return nn.GroupNorm(groups, channels)
    raise ValueError(f"norm {kind!r}: expected one of {', '.join(NORMS)}")


def model_options(cfg: Mapping[str, Any]) -> dict:
    """Read the TinyUNet keyword arguments from the ``train`` params.

    Parameters
    ----------
    cfg : Mapping
        The validated ``train:`` section.

    Returns
    -------
    dict
        ``norm`` and ``bn_momentum``.
    """
    return {"norm": str(cfg["norm"]), "bn_momentum": float(cfg["bn_momentum"])}


#: SIMD lanes the CPU's channels_last BatchNorm kernels vectorise over (AVX-512: 16 floats, 32 bf16): a channel
#: count that is not a multiple of it leaves a tail in every pixel's row, and aten's kernel slows 3-4x (24 channels)
_LANES = 16
#: the fewest pixels (N H W) a batch takes the wide view at: below it the view's extra small ops cost more than the
#: tail (per pixel count, interleaved with aten's, AMX host: 0.69x at 4 096, 0.94x at 32 768, 1.10x at 73 728, 1.31x
#: at 131 072 and 1.44x at 294 912 -- aten's time over the view's; docs/performance.md)
_WIDE_MIN_PIXELS = 65536


def _wide_columns(channels: int) -> int:
    """Count the pixels per row of the wide view: the fewest k with k * channels a multiple of 32 (bf16 lanes)."""
    k = 1
    while (k * channels) % (2 * _LANES):
        k += 1
    return k


#: the largest |scale| or |shift| of the affine map for which :func:`_affine_output_is_nan_free` vouches, far
#: below float's overflow so that aten's own rounding of the same two numbers cannot overflow either
_AFFINE_BOUND = 1e30


def _affine_output_is_nan_free(mean: torch.Tensor, var: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor,
                               eps: float) -> bool:
    """Tell whether BatchNorm's affine map can give no NaN on the batch its statistics came from.

    The map is y = a x + b with a = gamma / sqrt(sigma^2 + eps) and b = beta - mu a.  Finite per-channel statistics
    mean every input was finite (an inf or NaN input makes its channel's mean or variance inf or NaN), and a NaN
    output then needs an inf or NaN ``a`` or ``b`` (inf * 0, inf - inf); both are checked, with
    :data:`_AFFINE_BOUND` as margin.  One host read of a few dozen floats per block.

    Parameters
    ----------
    mean, var : torch.Tensor
        The batch's per-channel mean and biased variance (float).
    weight, bias : torch.Tensor
        gamma and beta.
    eps : float
        BatchNorm's epsilon.

    Returns
    -------
    bool
        True where no output can be NaN; False where one might (the caller then takes aten's ReLU).
    """
    with torch.no_grad():
        scale = weight.float() * torch.rsqrt(var + eps)
        shift = bias.float() - mean * scale
        both = torch.cat([mean, var, scale, shift])
        return bool((torch.isfinite(both) & (both.abs() <= _AFFINE_BOUND)).all())


def _relu_by_sign_bit_(y: torch.Tensor) -> torch.Tensor:
    """ReLU a NaN-free bf16 tensor in place through its bits: max(y, 0) as 16-bit integers.

    A bf16 number is negative exactly where its sign bit, the integer's, is set, so the integer clamp at 0 maps
    every negative number to +0 and keeps every other one: aten's ReLU, bit for bit, except that -0.0 becomes +0.0
    (equal values).  A NaN whose sign bit is set (bf16's own NaN, 0xFFFF) would become 0 where aten keeps it, so the
    caller vouches for no NaN (:func:`_affine_output_is_nan_free`).  Why: aten's bf16 ReLU converts to float and
    back: 4-5x the time of the integer clamp on a 6 MB tensor out of cache; in `distill`'s 128² step on AMX the
    forward is 2-4 ms shorter (docs/performance.md).

    Parameters
    ----------
    y : torch.Tensor
        bf16, contiguous, no NaN.

    Returns
    -------
    torch.Tensor
        ``y``, rectified.
    """
    y.view(torch.int16).clamp_min_(0)
    return y


class _WideBatchNormReLU(torch.autograd.Function):
    """Training-mode BatchNorm + ReLU on a channels_last tensor, computed on a wide 2-D view of its memory.

    The channels_last memory of x [N, C, H, W] is a matrix [N H W, C]; viewed as [N H W / k, k C] with k C a
    multiple of the SIMD width, aten's 2-D BatchNorm kernels (statistics, the affine map, the backward's sums)
    vectorise fully.  The k column groups are combined per channel: the mean of the k means, and the mean of the k
    biased variances plus the variance of the k means (equal group sizes: the exact pooled variance).  The backward
    is aten's eval-mode BatchNorm backward on the wide view (dx = gamma invstd g, and the per-column sums of g and of
    g x_hat), plus the training-mode terms -gamma invstd (sum g + x_hat sum g x_hat) / M as one more affine map,
    with the ReLU's mask applied first.  The ReLU works on the bf16 bits as 16-bit integers where the affine map can
    give no NaN (:func:`_relu_by_sign_bit_`; aten's float kernel otherwise), the same values as aten's.  Every
    coefficient stays float; only tensors round to
    the input's dtype, as in aten's kernel.
    """

    @staticmethod
    def forward(ctx, x, weight, bias, running_mean, running_var, momentum: float, eps: float):
        n, c, h, w = x.shape
        m = n * h * w
        k = _wide_columns(c)
        xv = x.permute(0, 2, 3, 1).reshape(m // k, k * c)
        # float statistics of a bf16 input need float running buffers; momentum 0 leaves these scratch ones as given
        mean_k, var_k = torch.batch_norm_update_stats(xv, torch.zeros(k * c, device=x.device),
                                                      torch.ones(k * c, device=x.device), 0.0)
        mean_k, var_k = mean_k.view(k, c), var_k.view(k, c)
        mean = mean_k.mean(0)
        var = var_k.mean(0) + (mean_k - mean).square().mean(0)
        with torch.no_grad():
            running_mean.mul_(1 - momentum).add_(mean, alpha=momentum)
            running_var.mul_(1 - momentum).add_(var * (m / max(m - 1, 1)), alpha=momentum)
        # per column (the channel's value repeated k times), computed once for the forward and the backward
        mean_col, var_col, weight_col = mean.repeat(k), var.repeat(k), weight.repeat(k)
        yv = F.batch_norm(xv, mean_col, var_col, weight_col, bias.repeat(k), False, 0.0, eps)
        if _affine_output_is_nan_free(mean, var, weight, bias, eps):
            _relu_by_sign_bit_(yv)
        else:
            yv.relu_()
        ctx.save_for_backward(xv, yv, weight, mean, var, weight_col, mean_col, var_col)
        ctx.shape, ctx.k, ctx.eps = (n, c, h, w), k, eps
        return yv.view(n, h, w, c).permute(0, 3, 1, 2)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        xv, yv, weight, mean, var, weight_col, mean_col, var_col = ctx.saved_tensors
        (n, c, h, w), k, eps = ctx.shape, ctx.k, ctx.eps
        m = n * h * w
        gv = grad.contiguous(memory_format=torch.channels_last).permute(0, 2, 3, 1).reshape(m // k, k * c)
        gz = torch.ops.aten.threshold_backward(gv, yv, 0)
        dxv, dot_k, sum_k = torch.ops.aten.native_batch_norm_backward(
            gz, xv, weight_col, mean_col, var_col, None, None, False, eps, [True, True, True])
        sum_g, dot = sum_k.view(k, c).sum(0), dot_k.view(k, c).sum(0)  # sum g and sum g x_hat per channel
        invstd = torch.rsqrt(var + eps)
        alpha = -weight * invstd * invstd * dot / m  # dx += alpha x + beta
        beta = -weight * invstd * sum_g / m - alpha * mean
        zeros, ones = torch.zeros_like(mean_col), torch.ones_like(var_col)
        # eval-mode batch_norm with mean 0, variance 1 and eps 0 is the float affine map alpha x + beta, rounded once
        dxv += F.batch_norm(xv, zeros, ones, alpha.repeat(k), beta.repeat(k), False, 0.0, 0.0)
        return dxv.view(n, h, w, c).permute(0, 3, 1, 2), dot, sum_g, None, None, None, None


def _wide_path_applies(x: torch.Tensor, norm: nn.Module) -> bool:
    """Whether :func:`batch_norm_relu` takes the wide view (see there); otherwise aten's own kernels run."""
    return (isinstance(norm, nn.BatchNorm2d) and norm.training and norm.track_running_stats and norm.affine
            and norm.momentum is not None and not norm._forward_hooks and not norm._forward_pre_hooks
            and x.dtype == torch.bfloat16 and x.device.type == "cpu" and x.dim() == 4
            and x.shape[1] % _LANES != 0 and x.numel() % (_wide_columns(x.shape[1]) * x.shape[1]) == 0
            and x.is_contiguous(memory_format=torch.channels_last)
            and x.shape[0] * x.shape[2] * x.shape[3] >= max(_WIDE_MIN_PIXELS, 2))


def batch_norm_relu(x: torch.Tensor, norm: nn.Module, relu: nn.Module | None = None) -> torch.Tensor:
    """Apply ``norm`` then a ReLU: relu(gamma (x - mu) / sqrt(sigma^2 + eps) + beta), mu and sigma^2 per channel.

    In training, bf16 on a CPU, channels_last, at least :data:`_WIDE_MIN_PIXELS` pixels a batch, with a channel
    count that is not a multiple of the SIMD width (the TinyUNet's 24), aten's channels_last BatchNorm leaves part of
    each vector empty; :class:`_WideBatchNormReLU` computes the same function on a wide view of the same memory
    instead (forward and backward for 8 x 24 x 128², interleaved with aten's: 13.1 against 17.1 ms;
    docs/performance.md): within bf16 rounding of a float64 reference and no further from it than aten's kernel
    (tests/core/test_model.py; where the ReLU's input is within rounding of 0 the two may pick different sides, as
    any two roundings may), with the same running statistics and ``num_batches_tracked``.  Everything else (fp32,
    so that fp32 runs keep their bits; fewer pixels; eval; NCHW; hooks on ``norm``; a cumulative momentum) runs
    aten's kernels.

    Parameters
    ----------
    x : torch.Tensor
        The convolution's output [N, C, H, W].
    norm : nn.Module
        The block's normalisation (BatchNorm2d or GroupNorm).
    relu : nn.Module or None
        The block's ReLU module, called on aten's path so that traces and exports see the module they always saw
        (None: the in-place functional ReLU).

    Returns
    -------
    torch.Tensor
        The block's output, channels_last where ``x`` is.
    """
    if not _wide_path_applies(x, norm):
        return relu(norm(x)) if relu is not None else F.relu(norm(x), inplace=True)
    norm.num_batches_tracked.add_(1)
    return _WideBatchNormReLU.apply(x, norm.weight, norm.bias, norm.running_mean, norm.running_var,
                                    float(norm.momentum), float(norm.eps))


class ConvBNReLU(nn.Sequential):
    """A 3x3 convolution without bias, its normalisation and a ReLU.

    Parameters
    ----------
    cin : int
        Input channels.
    cout : int
        Output channels.
    norm : str
        One of :data:`NORMS` (the first, BatchNorm, unless given).
    bn_momentum : float
        BatchNorm's running-statistics momentum (``train.bn_momentum`` unless given).
    """

    def __init__(self, cin: int, cout: int, norm: str = NORMS[0], bn_momentum: float = PAPER.train.bn_momentum):
        super().__init__(nn.Conv2d(cin, cout, 3, padding=1, bias=False), norm_layer(norm, cout, bn_momentum),
                         nn.ReLU(inplace=True))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Compute relu(norm(conv(x))) through :func:`batch_norm_relu`.

        Parameters
        ----------
        x : torch.Tensor
            [N, cin, H, W].

        Returns
        -------
        torch.Tensor
            [N, cout, H, W].
        """
        conv, norm, relu = self
        return batch_norm_relu(conv(x), norm, relu)


class DoubleConv(nn.Sequential):
    """Two :class:`ConvBNReLU`, the second keeping the channels: one level of the U-Net."""

    def __init__(self, cin: int, cout: int, **norm: Any):
        super().__init__(ConvBNReLU(cin, cout, **norm), ConvBNReLU(cout, cout, **norm))


def _bn_affine(bn: nn.BatchNorm2d) -> tuple[torch.Tensor, torch.Tensor]:
    """Write eval-mode BatchNorm as y = s x + t per channel, float64: s = gamma / sqrt(var + eps), t = beta - s mu."""
    s = bn.weight.double() / torch.sqrt(bn.running_var.double() + bn.eps)
    return s, bn.bias.double() - s * bn.running_mean.double()


class ExpandedConvBNReLU(nn.Module):
    """A :class:`ConvBNReLU` trained with RepVGG's extra linear branches (Ding et al., CVPR 2021).

    The block of ``train.expand_branches``.

    relu(BN_3(W_3 * x) + BN_1(W_1 * x) + BN_id(x)): the 3x3 convolution and its BatchNorm (the plain block's own
    modules), a 1x1 convolution with its own BatchNorm, and, where input and output channels match at stride 1, an
    identity branch that is a BatchNorm alone.  In eval mode every branch is affine in x, so the sum is one 3x3
    convolution plus a bias (:meth:`folded`): the capacity is training-time only.  Per-branch BN cannot fold under
    GroupNorm (its statistics are per sample), so the block needs BatchNorm.

    Parameters
    ----------
    block : ConvBNReLU
        The plain block; its convolution and BatchNorm become the 3x3 branch (shared, not copied).
    zero_init : bool
        Start the new branches at zero (their BN gamma 0), so the block computes exactly ``block``'s function
        (a warm start: Stage II from a folded Stage-I checkpoint); False = PyTorch's initialisation (gamma 1), as
        RepVGG trains from scratch.
    """

    def __init__(self, block: ConvBNReLU, zero_init: bool):
        """Add the 1x1 and identity branches beside ``block``'s own convolution and BatchNorm.

        Raises
        ------
        ValueError
            ``block``'s normalisation is not BatchNorm.
        """
        super().__init__()
        conv, norm = block[0], block[1]
        if not isinstance(norm, nn.BatchNorm2d):
            raise ValueError(f"RepVGG branches fold only through BatchNorm, not {type(norm).__name__}")
        cin, cout = conv.in_channels, conv.out_channels
        like = {"device": conv.weight.device, "dtype": conv.weight.dtype}
        self.conv, self.norm, self.relu = conv, norm, block[2]
        self.conv1x1 = nn.Conv2d(cin, cout, 1, bias=False, **like)
        self.norm1x1 = nn.BatchNorm2d(cout, momentum=norm.momentum, **like)
        identity = cin == cout and tuple(conv.stride) == (1, 1)
        self.norm_identity = nn.BatchNorm2d(cout, momentum=norm.momentum, **like) if identity else None
        if zero_init:
            for bn in self.branch_norms():
                nn.init.zeros_(bn.weight)

    def branch_norms(self) -> list[nn.BatchNorm2d]:
        """List the BatchNorms of the extra branches.

        Returns
        -------
        list of nn.BatchNorm2d
            The 1x1 branch's, then the identity branch's where there is one.
        """
        return [self.norm1x1] + ([self.norm_identity] if self.norm_identity is not None else [])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Compute relu(BN_3(W_3 * x) + BN_1(W_1 * x) + BN_id(x)).

        Parameters
        ----------
        x : torch.Tensor
            Features [B, in, H, W].

        Returns
        -------
        torch.Tensor
            Features [B, out, H, W].
        """
        y = self.norm(self.conv(x)) + self.norm1x1(self.conv1x1(x))
        if self.norm_identity is not None:
            y = y + self.norm_identity(x)
        return self.relu(y)

    @torch.no_grad()
    def fused(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Fuse the eval-mode block before its ReLU into one 3x3 convolution, in float64.

        K = s_3 W_3 + s_1 pad(W_1) + s_id I and b = t_3 + t_1 + t_id, each BN in eval mode being s x + t per channel
        (:func:`_bn_affine`), pad(W_1) the 1x1 kernel at the centre of a 3x3 one and I the identity kernel (the
        zero padding of the 3x3 convolution leaves the centre taps exact at the border).

        Returns
        -------
        tuple of torch.Tensor
            (kernel K [out, in, 3, 3], bias b [out]), float64.
        """
        s3, t3 = _bn_affine(self.norm)
        s1, t1 = _bn_affine(self.norm1x1)
        kernel = self.conv.weight.double() * s3[:, None, None, None]
        kernel[:, :, 1, 1] += self.conv1x1.weight.double()[:, :, 0, 0] * s1[:, None]
        bias = t3 + t1
        if self.norm_identity is not None:
            sid, tid = _bn_affine(self.norm_identity)
            idx = torch.arange(kernel.shape[0], device=kernel.device)
            kernel[idx, idx, 1, 1] += sid
            bias = bias + tid
        return kernel, bias

    @torch.no_grad()
    def folded(self) -> ConvBNReLU:
        """Fold the block into the plain :class:`ConvBNReLU` (3x3 convolution, BatchNorm, ReLU) of the same eval output.

        Its convolution is W = a K, a per output channel the ratio of the 3x3 branch's kernel norm to ||K|| (so a
        later warm start steps the kernel at the scale the 3x3 branch trained at); its BatchNorm holds the mean
        a m and variance a^2 v of W x, m = sum_k s_k mu_k exact and v = (sum_k |s_k| sigma_k)^2 a bound (the
        branches' covariance is not kept; :func:`fold_branches` measures it given images), with
        gamma = sqrt(a^2 v + eps) / a and beta = b + m, so that BN(W x) = K x + b in eval mode.  Draws no random
        number.

        Returns
        -------
        ConvBNReLU
            The plain block, on this block's device and dtype.
        """
        kernel, bias = self.fused()
        sigma = lambda bn: torch.sqrt(bn.running_var.double())  # noqa: E731
        s3, _ = _bn_affine(self.norm)
        mean = s3 * self.norm.running_mean.double()
        spread = s3.abs() * sigma(self.norm)
        for bn in self.branch_norms():
            s, _ = _bn_affine(bn)
            mean, spread = mean + s * bn.running_mean.double(), spread + s.abs() * sigma(bn)
        k_norm = kernel.flatten(1).norm(dim=1)
        w3_norm = self.conv.weight.double().flatten(1).norm(dim=1)
        a = torch.where((k_norm > 0) & (w3_norm > 0), w3_norm / k_norm.clamp_min(1e-300), torch.ones_like(k_norm))
        with torch.random.fork_rng(devices=[]):  # the new convolution's initialisation is overwritten
            plain = ConvBNReLU(self.conv.in_channels, self.conv.out_channels, "batch", self.norm.momentum)
        plain = plain.to(device=self.conv.weight.device, dtype=self.conv.weight.dtype)
        conv, bn = plain[0], plain[1]
        bn.eps = self.norm.eps
        conv.weight.copy_(kernel * a[:, None, None, None])
        bn.running_mean.copy_(a * mean)
        bn.running_var.copy_(a * a * spread * spread)
        bn.weight.copy_(torch.sqrt(a * a * spread * spread + bn.eps) / a)
        bn.bias.copy_(bias + mean)
        bn.num_batches_tracked.copy_(self.norm.num_batches_tracked)
        return plain


def _double_convs(model: nn.Module) -> list[DoubleConv]:
    return [m for m in model.modules() if isinstance(m, DoubleConv)]


def has_branches(model: nn.Module) -> bool:
    """Tell whether ``model`` holds RepVGG training branches still to fold.

    Parameters
    ----------
    model : nn.Module
        A TinyUNet.

    Returns
    -------
    bool
        True when an :class:`ExpandedConvBNReLU` is in it.
    """
    return any(isinstance(m, ExpandedConvBNReLU) for m in model.modules())


def expand_branches(model: "TinyUNet", zero_init: bool = False) -> "TinyUNet":
    """Give every 3x3 convolution of ``model`` RepVGG's training branches (:class:`ExpandedConvBNReLU`), in place.

    The identity branch exists where input and output channels match: the second convolution of each of the five
    :class:`DoubleConv`, 5 of the 10.  The 3x3 branches are ``model``'s own modules (the same weights, the same
    random draws before this call); the new branches draw their initialisation from the global torch RNG.

    Parameters
    ----------
    model : TinyUNet
        A plain TinyUNet with BatchNorm (``train.norm: batch``).
    zero_init : bool
        New branches start at zero (:class:`ExpandedConvBNReLU`): the expanded model computes ``model``'s function.

    Returns
    -------
    TinyUNet
        ``model``, expanded.

    Raises
    ------
    ValueError
        ``model`` normalises with GroupNorm, or is expanded already.
    """
    if has_branches(model):
        raise ValueError("the model already holds RepVGG branches")
    for double in _double_convs(model):
        for i, block in enumerate(double):
            double[i] = ExpandedConvBNReLU(block, zero_init)
    return model


@torch.no_grad()
def fold_branches(model: "TinyUNet", batches: Iterable[torch.Tensor] | None = None) -> "TinyUNet":
    """Fold every :class:`ExpandedConvBNReLU` of ``model`` into a plain :class:`ConvBNReLU`, in place.

    The eval-mode function is kept (:meth:`ExpandedConvBNReLU.folded`: exact up to rounding, the fusion in float64);
    the result is the plain TinyUNet, whose state dict and ``config`` are those of a model trained without branches.
    With ``batches``, each folded BatchNorm's running mean and variance become those of its input over the batches
    (the mean of the batch means and of the unbiased batch variances, as :func:`recompute_bn_stats` averages),
    measured in eval mode and with gamma and beta set so that the eval function stays the same; training mode (a
    warm start) then normalises about as evaluation does.

    Parameters
    ----------
    model : TinyUNet
        A model expanded by :func:`expand_branches` (a plain one is returned unchanged).
    batches : iterable of torch.Tensor or None
        Images [B,3,H,W] on the model's device (the training images); None keeps the bound of
        :meth:`ExpandedConvBNReLU.folded` for the variance.

    Returns
    -------
    TinyUNet
        ``model``, folded, in the train/eval mode it was in.
    """
    folded: list[nn.BatchNorm2d] = []
    for double in _double_convs(model):
        for i, block in enumerate(double):
            if isinstance(block, ExpandedConvBNReLU):
                double[i] = block.folded().train(block.training)
                folded.append(double[i][1])
    if batches is None or not folded:
        return model
    sums = {id(bn): [0, 0.0, 0.0] for bn in folded}

    def collect(bn, args):  # per-channel batch statistics, summed in float64 (no float64 copy of the batch)
        x = args[0].float()
        acc = sums[id(bn)]
        acc[0] += 1
        acc[1] = acc[1] + x.mean(dim=(0, 2, 3)).double()
        acc[2] = acc[2] + x.var(dim=(0, 2, 3), unbiased=True).double()

    hooks = [bn.register_forward_pre_hook(collect) for bn in folded]
    was_training = model.training
    try:
        model.eval()
        for x in batches:
            model(x)
    finally:
        for h in hooks:
            h.remove()
        model.train(was_training)
    for bn in folded:
        n, mean_sum, var_sum = sums[id(bn)]
        if n:
            s, t = _bn_affine(bn)  # the eval function s x + t, kept
            mean, var = mean_sum / n, var_sum / n
            bn.running_mean.copy_(mean)
            bn.running_var.copy_(var)
            bn.weight.copy_(s * torch.sqrt(var + bn.eps))
            bn.bias.copy_(t + s * mean)
    return model


class GeometryHeads(nn.Module):
    """Training-only SDF (tanh) and skeleton (logit) heads on the shared decoded features (Stage II)."""

    def __init__(self, features: int):
        super().__init__()
        self.sdf = nn.Conv2d(features, 1, 1)
        self.skeleton = nn.Conv2d(features, 1, 1)

    def forward(self, feats: torch.Tensor) -> dict[str, torch.Tensor]:
        """Compute both heads: ``sdf`` D^S in [-1, 1] (tanh, eq:sdf-loss), ``skeleton`` logits (eq:skeleton-loss)."""
        return {"sdf": torch.tanh(self.sdf(feats)), "skeleton": self.skeleton(feats)}


def _dense_channels_last_grad(grad: torch.Tensor) -> torch.Tensor:
    return grad.contiguous(memory_format=torch.channels_last)


def _upsample(x: torch.Tensor, size) -> torch.Tensor:
    """Bilinear upsampling to ``size`` (the decoder's; align_corners False).

    Training in channels_last, the gradient reaching it is a channel slice of the skip concatenation's gradient,
    which is not channels_last-contiguous, and the CPU's upsampling backward then takes its slow path (about 10x, 13
    of a 138 ms bf16 step at 128²; docs/performance.md).  A hook makes that gradient contiguous first: the same
    numbers, bit for bit (tests/core/test_model.py), for one copy.
    """
    y = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
    if y.requires_grad and y.is_contiguous(memory_format=torch.channels_last):
        y.register_hook(_dense_channels_last_grad)
    return y


def _unet(m: nn.Module, x: torch.Tensor, sizes=None) -> torch.Tensor:
    """Decode ``x`` through ``m``'s encoder-decoder; ``sizes``: the two upsampling sizes (default: the skips')."""
    e1 = m.enc1(x)
    e2 = m.enc2(F.max_pool2d(e1, 2))
    e3 = m.enc3(F.max_pool2d(e2, 2))
    s2, s1 = sizes or (e2.shape[-2:], e1.shape[-2:])
    d2 = m.dec2(torch.cat([_upsample(e3, s2), e2], dim=1))
    return m.dec1(torch.cat([_upsample(d2, s1), e1], dim=1))


class TinyUNet(nn.Module):
    """The student: a three-level U-Net whose mask head gives the deployed logits Z.

    Images are float RGB in [0, 1], normalised inside the model by :attr:`MEAN` and :attr:`STD` so that exported
    models take the same input.  Stage II adds the training-only geometry heads (:meth:`add_geometry_heads`).

    Parameters
    ----------
    in_channels : int
        Input channels (RGB: 3).
    channels : Sequence of int
        The three encoder widths (``train.channels`` unless given).
    norm : str
        One of :data:`NORMS`; the first, BatchNorm (the paper's), is what a ``config`` without ``norm`` means.
    bn_momentum : float
        BatchNorm's running-statistics momentum (``train.bn_momentum`` unless given); acts in training only.

    Attributes
    ----------
    config : dict
        The keyword arguments that rebuild the deployed model (checkpoints, export): ``in_channels``,
        ``channels``, and ``norm`` only where it is not BatchNorm.
    geometry_heads : GeometryHeads or None
        The SDF and skeleton heads (Stage II training only).
    """

    # images are float in [0, 1], normalised inside the model so that exported models take the same input
    MEAN = 0.5
    STD = 0.25

    def __init__(self, in_channels: int = 3, channels: Sequence[int] = tuple(PAPER.train.channels),
                 norm: str = NORMS[0], bn_momentum: float = PAPER.train.bn_momentum):
        super().__init__()
        c1, c2, c3 = (int(c) for c in channels)
        # ``config`` rebuilds the deployed model (checkpoints, export): ``norm`` only where it is not the
        # paper's BatchNorm, so default checkpoints stay byte-identical; the momentum only acts in training
        self.config = {"in_channels": int(in_channels), "channels": [c1, c2, c3]}
        if norm != NORMS[0]:
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
        """Compute the decoded features the heads share.

        Parameters
        ----------
        x : torch.Tensor
            float RGB [B, 3, H, W] in [0, 1].

        Returns
        -------
        torch.Tensor
            Features [B, channels[0], H, W].
        """
        return _unet(self, (x - self.MEAN) / self.STD)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Compute the mask logits Z, the deployed output (eq:inference-mask thresholds sigmoid(Z)).

        Parameters
        ----------
        x : torch.Tensor
            float RGB [B, 3, H, W] in [0, 1].

        Returns
        -------
        torch.Tensor
            Z [B, 1, H, W].
        """
        return self.mask_head(self.decode(x))

    def add_geometry_heads(self) -> "TinyUNet":
        """Create fresh SDF and skeleton heads (start of Stage II); the mask path is untouched.

        Returns
        -------
        TinyUNet
            This model.
        """
        ref = self.mask_head.weight
        self.geometry_heads = GeometryHeads(self.config["channels"][0]).to(device=ref.device, dtype=ref.dtype)
        return self

    def forward_train(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """Compute every head's output for the training losses.

        Parameters
        ----------
        x : torch.Tensor
            float RGB [B, 3, H, W] in [0, 1].

        Returns
        -------
        dict
            ``mask`` logits [B, 1, H, W]; with the geometry heads, ``sdf`` (tanh) and ``skeleton`` logits too.
        """
        feats = self.decode(x)
        out = {"mask": self.mask_head(feats)}
        if self.geometry_heads is not None:
            out.update(self.geometry_heads(feats))
        return out

    def mask_path_state_dict(self) -> dict[str, torch.Tensor]:
        """Select the weights of the deployed path (no geometry heads).

        Returns
        -------
        dict
            The state dict less ``geometry_heads.*``.
        """
        return {k: v for k, v in self.state_dict().items() if not k.startswith("geometry_heads.")}


def mask_path_model(model: TinyUNet) -> TinyUNet:
    """Copy the deployed mask path: the TinyUNet without its geometry heads.

    Parameters
    ----------
    model : TinyUNet
        The student (any device, dtype or mode).

    Returns
    -------
    TinyUNet
        A float32 CPU copy in eval mode, without gradients.
    """
    deployed = TinyUNet(**model.config)
    deployed.load_state_dict(model.mask_path_state_dict())
    return deployed.float().eval().requires_grad_(False)


class ExportMaskPath(nn.Module):
    """A TinyUNet's mask path for export and int8 inference (docs/decisions.md).

    The normalisation is folded into the first convolution, conv(W, pad_0((x - m) / s)) = conv(W / s, pad_m(x)) -
    (m / s) sum(W); the upsampling sizes come from the input's shape.

    Parameters
    ----------
    unet : TinyUNet
        The plain student (copied, float32, eval mode).
    """

    def __init__(self, unet: TinyUNet):
        """Copy ``unet``'s mask path with its normalisation folded into the first convolution.

        Raises
        ------
        ValueError
            ``unet`` still holds RepVGG branches (:func:`fold_branches` first).
        """
        super().__init__()
        if has_branches(unet):
            raise ValueError("ExportMaskPath takes the plain TinyUNet: fold its RepVGG branches first "
                             "(pipeline.model.fold_branches)")
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
        """Compute the mask logits Z, as :meth:`TinyUNet.forward` does.

        Parameters
        ----------
        x : torch.Tensor
            float RGB [B, 3, H, W] in [0, 1].

        Returns
        -------
        torch.Tensor
            Z [B, 1, H, W].
        """
        h, w = x.shape[-2], x.shape[-1]
        return self.mask_head(_unet(self, F.pad(x, self.padding, value=self.pad_value), ((h // 2, w // 2), (h, w))))


@torch.no_grad()
def recompute_bn_stats(model: nn.Module, batches: Iterable[torch.Tensor]) -> int:
    """Recompute every BatchNorm's running statistics (precise BN, ``train.precise_bn``).

    They become the plain average of the batch statistics over ``batches`` with the current weights.

    Parameters
    ----------
    model : nn.Module
        The model (its train/eval mode is kept).
    batches : iterable of torch.Tensor
        Input batches on the model's device.

    Returns
    -------
    int
        The number of batches used (0: nothing changed).
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
    """Count a model's parameters.

    Parameters
    ----------
    model : nn.Module
        The model.
    deployed_only : bool
        Leave out the training-only geometry heads.

    Returns
    -------
    int
        The number of parameters.
    """
    return sum(p.numel() for n, p in model.named_parameters()
               if not (deployed_only and n.startswith("geometry_heads.")))


def count_flops(model: nn.Module, height: int = PAPER.data.resolution, width: int = PAPER.data.resolution) -> int:
    """Count the FLOPs of one forward pass (torch's FlopCounterMode: a multiply-add is 2).

    Parameters
    ----------
    model : nn.Module
        The model (the deployed mask path for the deployed figure).
    height : int
        The input's height (``data.resolution`` unless given).
    width : int
        The input's width (``data.resolution`` unless given).

    Returns
    -------
    int
        The FLOPs of a batch-1 forward pass.
    """
    from torch.utils.flop_counter import FlopCounterMode

    ref = next(model.parameters())
    x = torch.zeros(1, model.config["in_channels"], height, width, device=ref.device, dtype=ref.dtype)
    was_training = model.training
    model.eval()
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        model(x)
    model.train(was_training)
    return int(counter.get_total_flops())
