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
