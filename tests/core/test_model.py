"""TinyUNet: deployed size and cost, outputs of the deployed and training paths, geometry heads."""

from __future__ import annotations

import copy

import torch

from pipeline.model import TinyUNet, _affine_output_is_nan_free, count_flops, count_parameters


def test_deployed_parameter_count_matches_the_paper():
    m = TinyUNet()
    # paper: "approximately 0.263 M parameters"; ours (24/48/96, BN, bilinear up, 1x1 head) is exact:
    assert count_parameters(m) == 266_017
    m.add_geometry_heads()
    assert count_parameters(m) == 266_017  # geometry heads are training-only
    assert count_parameters(m, deployed_only=False) == 266_017 + 2 * (24 + 1)


def test_flops_at_384_counted_from_the_graph():
    # paper: about 18.2 GFLOPs at 384^2; FlopCounterMode (multiply-add = 2) gives 18.54 G
    flops = count_flops(TinyUNet(), 384, 384)
    assert flops == 18_544_066_560
    assert count_flops(TinyUNet(), 64, 64) * 36 == flops  # conv cost is linear in the pixel count


def test_forward_returns_mask_logits_and_forward_train_adds_heads():
    torch.manual_seed(0)
    m = TinyUNet().eval()
    x = torch.rand(2, 3, 32, 32)
    z = m(x)
    assert z.shape == (2, 1, 32, 32)
    assert set(m.forward_train(x)) == {"mask"}
    m.add_geometry_heads()
    out = m.forward_train(x)
    assert set(out) == {"mask", "sdf", "skeleton"}
    assert torch.equal(out["mask"], z)  # heads do not touch the mask path
    assert out["sdf"].abs().max() <= 1.0  # tanh head
    assert torch.equal(m(x), z)  # deployed forward unchanged: mask logits only
    assert not any(k.startswith("geometry_heads.") for k in m.mask_path_state_dict())
    fresh = TinyUNet()
    fresh.load_state_dict(m.mask_path_state_dict())  # the deployed path loads without the heads


def test_channels_last_and_bf16_autocast_agree_with_fp32():
    torch.manual_seed(0)
    m = TinyUNet().eval()
    x = torch.rand(1, 3, 32, 32)
    with torch.no_grad():
        ref = torch.sigmoid(m(x))
        mc = TinyUNet().eval()
        mc.load_state_dict(m.state_dict())
        mc = mc.to(memory_format=torch.channels_last)
        cl = torch.sigmoid(mc(x.contiguous(memory_format=torch.channels_last)))
        with torch.autocast("cpu", dtype=torch.bfloat16):
            bf = torch.sigmoid(mc(x.contiguous(memory_format=torch.channels_last)).float())
    assert torch.allclose(cl, ref, atol=1e-5)
    assert (bf - ref).abs().max() < 0.05


def test_channels_last_training_gives_the_upsampling_a_dense_gradient_with_the_same_numbers(monkeypatch):
    """The decoder's upsampling gets a channels_last-contiguous gradient (its fast CPU backward): every parameter
    gradient bit-identical to the path without the hook, in fp32 and under bf16 autocast."""
    from pipeline import model as model_module

    seen = []
    real = model_module._dense_channels_last_grad

    def counting(grad):
        out = real(grad)
        seen.append(out.is_contiguous(memory_format=torch.channels_last))
        return out

    def grads(hooked: bool, amp: bool) -> dict:
        monkeypatch.setattr(model_module, "_dense_channels_last_grad", counting if hooked else (lambda g: g))
        torch.manual_seed(0)
        net = TinyUNet().add_geometry_heads().to(memory_format=torch.channels_last).train()
        x = torch.rand(2, 3, 32, 32).contiguous(memory_format=torch.channels_last)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=amp):
            out = net.forward_train(x)
        sum(v.float().square().mean() for v in out.values()).backward()
        return {k: p.grad.clone() for k, p in net.named_parameters()}

    for amp in (False, True):
        seen.clear()
        hooked, plain = grads(True, amp), grads(False, amp)
        assert seen == [True, True]  # both upsamplings, once each
        assert all(torch.equal(hooked[k], plain[k]) for k in plain)
    # inference (no grad) registers nothing
    seen.clear()
    monkeypatch.setattr(model_module, "_dense_channels_last_grad", counting)
    with torch.no_grad():
        TinyUNet().to(memory_format=torch.channels_last).eval()(torch.rand(1, 3, 32, 32))
    assert seen == []


def _bn_relu_step(norm, x, grad, wide: bool) -> dict:
    """One training-mode BatchNorm + ReLU forward and backward in bf16 channels_last: :func:`batch_norm_relu` (the
    wide view where it applies) or aten's modules."""
    from pipeline.model import batch_norm_relu

    x = x.clone().requires_grad_(True)
    y = batch_norm_relu(x, norm) if wide else torch.relu(norm(x))
    y.backward(grad)
    return {"y": y.detach().double(), "dx": x.grad.double(), "gamma": norm.weight.grad.double(),
            "beta": norm.bias.grad.double(), "running_mean": norm.running_mean.double(),
            "running_var": norm.running_var.double(), "tracked": int(norm.num_batches_tracked)}


def _bn_relu_float64(norm, x, grad, active) -> dict:
    """The same step in float64 from the same bf16 inputs, with the ReLU's mask ``active`` given: a ReLU's
    gradient jumps where its input crosses 0, so each path is held to the reference of its own mask."""
    x, g = x.double(), grad.double() * active
    mean, var = x.mean(dim=(0, 2, 3), keepdim=True), x.var(dim=(0, 2, 3), unbiased=False, keepdim=True)
    invstd = (var + norm.eps).rsqrt()
    xhat = (x - mean) * invstd
    w = norm.weight.double().view(1, -1, 1, 1)
    m = x.numel() // x.shape[1]
    dx = w * invstd * (g - g.mean(dim=(0, 2, 3), keepdim=True)
                       - xhat * (g * xhat).mean(dim=(0, 2, 3), keepdim=True))
    return {"y": torch.relu(xhat * w + norm.bias.double().view(1, -1, 1, 1)), "dx": dx,
            "gamma": (g * xhat).sum(dim=(0, 2, 3)), "beta": g.sum(dim=(0, 2, 3)),
            "running_mean": 0.9 * norm.running_mean.double() + 0.1 * mean.flatten(),
            "running_var": 0.9 * norm.running_var.double() + 0.1 * var.flatten() * m / (m - 1)}


def test_wide_batch_norm_relu_is_as_accurate_as_aten(monkeypatch):
    """The 24-channel BatchNorm + ReLU on the wide view (bf16, channels_last, training) against a float64
    reference: its output, gradients and running statistics are within bf16 rounding of it, no further from it
    than aten's kernel is (beside a margin of two bf16 steps), and it counts the batch; 48 channels keep aten's
    kernel."""

    from pipeline import model as model_module

    calls = []
    real = model_module._WideBatchNormReLU.apply
    monkeypatch.setattr(model_module._WideBatchNormReLU, "apply", lambda *a: calls.append(1) or real(*a))
    monkeypatch.setattr(model_module, "_WIDE_MIN_PIXELS", 1)  # tiny tensors take the view too
    for channels in (24, 48):
        torch.manual_seed(channels)
        norm = torch.nn.BatchNorm2d(channels).train()
        with torch.no_grad():  # non-trivial affine parameters and running statistics
            norm.weight.uniform_(0.5, 1.5)
            norm.bias.uniform_(-0.3, 0.3)
            norm.running_mean.uniform_(-0.1, 0.1)
        x = (torch.randn(4, channels, 16, 12) * 2 + 0.5).to(torch.bfloat16).contiguous(memory_format=torch.channels_last)
        grad = torch.randn(x.shape).to(torch.bfloat16).contiguous(memory_format=torch.channels_last)
        calls.clear()
        before = copy.deepcopy(norm)
        got = _bn_relu_step(norm, x, grad, wide=True)
        aten = _bn_relu_step(copy.deepcopy(before), x, grad, wide=False)
        assert calls == ([1] if channels % 16 else [])
        assert got["tracked"] == aten["tracked"] == 1
        ref = _bn_relu_float64(before, x, grad, got["y"] > 0)
        for key, want in ref.items():
            err, scale = (got[key] - want).abs().max().item(), want.abs().max().item()
            # bf16 tensors round once (2^-8 relative); the sums and statistics are kept in float
            assert err <= scale * (2.0 ** -7 if key in ("y", "dx") else 1e-3) + 1e-6, (channels, key, err, scale)
        ref_aten = _bn_relu_float64(before, x, grad, aten["y"] > 0)
        for key in ("y", "dx", "gamma", "beta"):
            err = (got[key] - ref[key]).abs().max().item()
            err_aten = (aten[key] - ref_aten[key]).abs().max().item()
            assert err <= err_aten + 2 * 2.0 ** -8 * ref[key].abs().max().item(), (channels, key, err, err_aten)


def _bf16_patterns() -> torch.Tensor:
    """Every one of the 65,536 bf16 bit patterns, as bf16."""
    return torch.arange(-(2 ** 15), 2 ** 15, dtype=torch.int32).to(torch.int16).view(torch.bfloat16)


def test_relu_by_sign_bit_is_atens_relu_on_every_bf16_number():
    """The integer ReLU against aten's float kernel over every bf16 bit pattern: the same bits everywhere but -0.0
    (+0.0: an equal value) and the NaNs, which the wide path never hands it (each would become 0); and aten's
    backward mask on its output is the mask on aten's own output, bit for bit."""
    from pipeline.model import _relu_by_sign_bit_

    x = _bf16_patterns()
    got, want = _relu_by_sign_bit_(x.clone()), torch.relu(x)
    nan, negative_zero = torch.isnan(x), x.view(torch.int16) == -(2 ** 15)
    same = torch.eq(got.view(torch.int16), want.view(torch.int16))
    assert bool(same[~nan & ~negative_zero].all())
    assert bool(torch.eq(got[negative_zero], want[negative_zero]).all())  # -0.0 -> +0.0, equal values
    assert int(nan.sum()) == 254 and not bool(torch.isnan(got[~nan]).any())
    g = x[torch.randperm(len(x), generator=torch.Generator().manual_seed(0))]
    keep = ~nan
    assert torch.equal(torch.ops.aten.threshold_backward(g[keep], got[keep], 0).view(torch.int16),
                       torch.ops.aten.threshold_backward(g[keep], want[keep], 0).view(torch.int16))


def test_affine_output_is_nan_free_refuses_what_could_give_a_nan():
    """The guard of the integer ReLU: True for ordinary statistics, False for an inf or NaN statistic, an overflowing
    scale (inf * 0 would be NaN) or a huge shift."""
    from pipeline.model import _affine_output_is_nan_free

    mean, var, w, b = torch.zeros(24), torch.ones(24), torch.ones(24), torch.zeros(24)
    assert _affine_output_is_nan_free(mean, var, w, b, 1e-5)
    for name, value in (("mean", float("nan")), ("mean", float("inf")), ("var", float("inf")),
                        ("var", float("nan")), ("w", 1e36), ("b", float("-inf")), ("b", 1e31)):
        args = {"mean": mean.clone(), "var": var.clone(), "w": w.clone(), "b": b.clone()}
        args[name][3] = value
        assert not _affine_output_is_nan_free(args["mean"], args["var"], args["w"], args["b"], 1e-5), (name, value)


def test_wide_batch_norm_relu_gives_aten_relus_bits_and_keeps_nans(monkeypatch):
    """The wide block with the integer ReLU against the same block with aten's ReLU (the guard forced False): the
    same output values, gradients and running statistics bit for bit; a NaN in the input takes aten's ReLU, so
    the NaN reaches the output as it would through aten's modules."""
    from pipeline import model as model_module
    from pipeline.model import batch_norm_relu

    monkeypatch.setattr(model_module, "_WIDE_MIN_PIXELS", 1)
    torch.manual_seed(3)
    base = torch.nn.BatchNorm2d(24).train()
    with torch.no_grad():
        base.weight.uniform_(-1.5, 1.5)  # negative gammas too
        base.bias.uniform_(-0.3, 0.3)
    x = (torch.randn(4, 24, 16, 12) * 2).to(torch.bfloat16).contiguous(memory_format=torch.channels_last)
    grad = torch.randn(x.shape).to(torch.bfloat16).contiguous(memory_format=torch.channels_last)
    runs = {}
    for guard in (True, False):
        norm = copy.deepcopy(base)
        monkeypatch.setattr(model_module, "_affine_output_is_nan_free",
                            _affine_output_is_nan_free if guard else lambda *a: False)
        xi = x.clone().requires_grad_(True)
        y = batch_norm_relu(xi, norm)
        y.backward(grad)
        runs[guard] = (y.detach(), xi.grad, norm.weight.grad, norm.bias.grad, norm.running_mean, norm.running_var)
    assert bool((runs[True][0] > 0).any()) and bool((runs[True][0] == 0).any())
    assert torch.equal(runs[True][0], runs[False][0])
    for a, b in zip(runs[True][1:], runs[False][1:]):
        assert torch.equal(a.view(torch.int16) if a.dtype == torch.bfloat16 else a,
                           b.view(torch.int16) if b.dtype == torch.bfloat16 else b)
    monkeypatch.setattr(model_module, "_affine_output_is_nan_free", _affine_output_is_nan_free)
    x_nan = x.clone()
    x_nan[0, 5, 3, 4] = float("nan")
    with torch.no_grad():
        norm = copy.deepcopy(base)
        y = batch_norm_relu(x_nan, norm)
        ref = torch.relu(copy.deepcopy(base)(x_nan))
    assert torch.equal(torch.isnan(y), torch.isnan(ref)) and bool(torch.isnan(y[:, 5]).all())


def test_wide_batch_norm_relu_leaves_fp32_eval_and_nchw_to_aten(monkeypatch):
    """fp32 (its bits kept), too few pixels, eval, NCHW and a cumulative momentum take aten's path: the same bits as
    the modules."""
    from pipeline import model as model_module
    from pipeline.model import ConvBNReLU, _wide_path_applies, batch_norm_relu

    torch.manual_seed(1)
    block = ConvBNReLU(3, 24).train()
    x = torch.rand(2, 3, 8, 8).contiguous(memory_format=torch.channels_last)
    assert torch.equal(block(x), block[2](block[1](block[0](x))))  # fp32 channels_last training
    calls = []
    real = model_module._WideBatchNormReLU.apply
    monkeypatch.setattr(model_module._WideBatchNormReLU, "apply", lambda *a: calls.append(1) or real(*a))
    with torch.autocast("cpu", dtype=torch.bfloat16):  # 2 x 8 x 8 pixels: too few for the view
        block(x)
    assert calls == []
    monkeypatch.setattr(model_module, "_WIDE_MIN_PIXELS", 2 * 8 * 8)
    with torch.autocast("cpu", dtype=torch.bfloat16):  # enough pixels: the block itself takes the wide view
        wide, plain = block(x), block[2](block[1](block[0](x)))
    assert calls == [1] and (wide.float() - plain.float()).abs().max() <= 2.0 ** -6 * plain.float().abs().max()
    y = block[0](x).to(torch.bfloat16)
    monkeypatch.setattr(model_module, "_WIDE_MIN_PIXELS", 2 * 8 * 8 + 1)
    assert not _wide_path_applies(y, block[1])  # one pixel short
    monkeypatch.setattr(model_module, "_WIDE_MIN_PIXELS", 2 * 8 * 8)
    assert not _wide_path_applies(y.contiguous(), block[1])  # NCHW
    assert _wide_path_applies(y, block[1])
    block[1].momentum = None
    assert not _wide_path_applies(y, block[1])  # recompute_bn_stats' cumulative average
    block[1].momentum = 0.1
    block.eval()
    assert not _wide_path_applies(y, block[1])
    with torch.no_grad():
        assert torch.equal(batch_norm_relu(y, block[1]), torch.relu(block[1](y)))

