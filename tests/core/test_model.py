"""TinyUNet: deployed size and cost, outputs of the deployed and training paths, geometry heads."""

from __future__ import annotations

import torch

from pipeline.model import TinyUNet, count_flops, count_parameters


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


def _block_step(block, x, grad, wide: bool):
    """One bf16 forward and backward of a ConvBNReLU; ``wide`` False runs aten's modules one after the other."""
    x = x.clone().requires_grad_(True)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = block(x) if wide else block[2](block[1](block[0](x)))
    y.backward(grad.to(y.dtype))
    bn = block[1]
    return {"y": y.float(), "dx": x.grad, "conv": block[0].weight.grad, "gamma": bn.weight.grad, "beta": bn.bias.grad,
            "running_mean": bn.running_mean, "running_var": bn.running_var, "tracked": bn.num_batches_tracked}


def test_wide_batch_norm_relu_matches_aten_within_bf16_rounding(monkeypatch):
    """The 24-channel BatchNorm + ReLU on the wide view (bf16, channels_last, training) gives aten's outputs,
    gradients and running statistics within bf16 rounding, and counts the batch; 48 channels keep aten's kernel."""
    import copy

    from pipeline import model as model_module
    from pipeline.model import ConvBNReLU

    calls = []
    real = model_module._WideBatchNormReLU.apply
    torch.manual_seed(0)
    for cin, cout in ((3, 24), (24, 48)):
        block = ConvBNReLU(cin, cout).train()
        with torch.no_grad():  # non-trivial affine parameters and running statistics
            block[1].weight.uniform_(0.5, 1.5)
            block[1].bias.uniform_(-0.3, 0.3)
            block[1].running_mean.uniform_(-0.1, 0.1)
        reference = copy.deepcopy(block)
        x = (torch.randn(4, cin, 16, 12) * 2 + 0.5).contiguous(memory_format=torch.channels_last)
        grad = torch.randn(4, cout, 16, 12).contiguous(memory_format=torch.channels_last)
        calls.clear()
        monkeypatch.setattr(model_module._WideBatchNormReLU, "apply", lambda *a: calls.append(1) or real(*a))
        got = _block_step(block, x, grad, wide=True)
        monkeypatch.undo()
        want = _block_step(reference, x, grad, wide=False)
        assert calls == ([1] if cout % 16 else [])
        assert got["y"].is_contiguous(memory_format=torch.channels_last)
        assert got["dx"].is_contiguous(memory_format=torch.channels_last)
        for key, ref in want.items():
            diff = (got[key].float() - ref.float()).abs().max().item()
            scale = ref.float().abs().max().item()
            # bf16 tensors: one rounding step (2^-8 of the largest value); float statistics: float rounding
            assert diff <= scale * (2.0 ** -7 if key in ("y", "dx", "conv") else 1e-3) + 1e-6, (cout, key, diff, scale)
        assert int(got["tracked"]) == 1


def test_wide_batch_norm_relu_leaves_fp32_eval_and_nchw_to_aten():
    """fp32 (its bits kept), eval, NCHW and a cumulative momentum take aten's path: the same bits as the modules."""
    from pipeline.model import ConvBNReLU, _wide_path_applies, batch_norm_relu

    torch.manual_seed(1)
    block = ConvBNReLU(3, 24).train()
    x = torch.rand(2, 3, 8, 8).contiguous(memory_format=torch.channels_last)
    assert torch.equal(block(x), block[2](block[1](block[0](x))))  # fp32 channels_last training
    y = block[0](x).to(torch.bfloat16)
    assert not _wide_path_applies(y.contiguous(), block[1])  # NCHW
    assert _wide_path_applies(y, block[1])
    block[1].momentum = None
    assert not _wide_path_applies(y, block[1])  # recompute_bn_stats' cumulative average
    block[1].momentum = 0.1
    block.eval()
    assert not _wide_path_applies(y, block[1])
    with torch.no_grad():
        assert torch.equal(batch_norm_relu(y, block[1]), torch.relu(block[1](y)))

