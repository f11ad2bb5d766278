"""Training and the SAM 3 teacher reuse freed memory (``pipeline.runtime.device.reuse_freed_memory``): glibc's
two malloc settings, left alone where the user chose their own, applied by ``train()``, the ``--time`` probe and
the teacher's load, and the same trained bits with and without them."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from pipeline.runtime import device
from tests.builders.training import REPO, shape_mask, tiny_cfg


class FakeLibc:
    """A C library whose ``mallopt`` records its calls (glibc: it has ``gnu_get_libc_version``)."""

    def __init__(self, glibc: bool = True, accepts: int = 1):
        self.calls = []
        self.accepts = accepts
        if glibc:
            self.gnu_get_libc_version = lambda: b"2.41"

    def mallopt(self, param, value):
        self.calls.append((param, value))
        return self.accepts


@pytest.fixture
def fresh(monkeypatch):
    """The module as in a process that has not applied the settings, with no glibc malloc setting of its own."""
    monkeypatch.setattr(device, "_FREED_MEMORY_REUSED", False)
    for name in device.GLIBC_MALLOC_ENV:
        monkeypatch.delenv(name, raising=False)
    return monkeypatch


def test_the_heap_keeps_what_a_step_frees(fresh):
    libc = FakeLibc()
    assert device.reuse_freed_memory(libc=libc) is True
    # M_MMAP_MAX (-4) 0: every block from the heap; M_TRIM_THRESHOLD (-1) 1 GiB (malloc.h)
    assert libc.calls == [(-4, 0), (-1, 2**30)]
    assert device.reuse_freed_memory(libc=FakeLibc()) is True  # once per process
    assert device.reuse_freed_memory() is True


@pytest.mark.parametrize("name", device.GLIBC_MALLOC_ENV)
def test_a_users_own_malloc_setting_is_left_as_chosen(fresh, name):
    fresh.setenv(name, "131072")
    libc = FakeLibc()
    assert device.reuse_freed_memory(libc=libc) is False and libc.calls == []


def test_another_c_library_or_a_refused_setting_is_left_alone(fresh):
    other = FakeLibc(glibc=False)
    assert device.reuse_freed_memory(libc=other) is False and other.calls == []
    refused = FakeLibc(accepts=0)
    assert device.reuse_freed_memory(libc=refused) is False
    assert device.reuse_freed_memory(libc=FakeLibc()) is True  # a refusal is not remembered as done


def test_a_gpu_leaves_malloc_alone(fresh):
    libc = FakeLibc()
    assert device.reuse_freed_memory("cuda:0", libc=libc) is False and libc.calls == []


def test_train_and_the_time_probe_reuse_the_heap_on_a_cpu(monkeypatch):
    from pipeline.methods import get_method
    from pipeline.profiles import load_profile
    from pipeline.training import budget, loop
    from pipeline.training.checkpointing import NoCheckpointer

    seen = []
    monkeypatch.setattr(loop, "reuse_freed_memory", lambda device: seen.append("train"))
    monkeypatch.setattr(budget, "reuse_freed_memory", lambda device: seen.append("probe"))
    assert budget.step_seconds(load_profile("distill", ["train.channels=[4,8,16]"])["train"], 16) > 0
    rng = np.random.default_rng(0)
    masks = np.stack([shape_mask(rng, 16) for _ in range(2)])
    images = np.where(masks[..., None], 200, rng.integers(0, 40, (2, 16, 16, 3))).astype(np.uint8)
    data = loop.TrainData(image_ids=["a", "b"], images=images, mask=masks, area=masks.reshape(2, -1).mean(1),
                          gate=np.ones(2, np.float32))
    loop.train(get_method("plain"), tiny_cfg(epochs_stage1=1, batch_size=2), data, None, 0,
               checkpointer=NoCheckpointer(), show_progress=False)
    assert seen == ["probe", "train"]


TRAIN_STEPS = """
import hashlib, json, torch
from pipeline.model import TinyUNet
from pipeline.runtime.device import reuse_freed_memory
applied = reuse_freed_memory()
torch.manual_seed(0); torch.set_num_threads(1)
m = TinyUNet().train()
opt = torch.optim.AdamW(m.parameters(), 1e-3)
x, t = torch.rand(4, 3, 64, 64), (torch.rand(4, 1, 64, 64) > 0.5).float()
for _ in range(3):  # fp32, 1.5 MiB activations: above glibc's default mmap threshold, so mapped afresh without it
    loss = torch.nn.functional.binary_cross_entropy_with_logits(m(x), t)
    opt.zero_grad(); loss.backward(); opt.step()
digest = hashlib.sha256(b"".join(v.numpy().tobytes() for v in m.state_dict().values())).hexdigest()
print(json.dumps({"applied": applied, "digest": digest}))
"""


def test_the_same_bits_with_and_without_the_heap_reuse():
    if not hasattr(__import__("ctypes").CDLL(None), "gnu_get_libc_version"):
        pytest.skip("not glibc")
    env = {k: v for k, v in os.environ.items() if k not in device.GLIBC_MALLOC_ENV}
    runs = [json.loads(subprocess.run([sys.executable, "-c", TRAIN_STEPS], cwd=REPO, env=e, check=True,
                                      capture_output=True, text=True).stdout)
            for e in (env, {**env, "MALLOC_TRIM_THRESHOLD_": "131072"})]
    assert [r["applied"] for r in runs] == [True, False]
    assert runs[0]["digest"] == runs[1]["digest"]


def test_the_sam3_teacher_reuses_the_heap_on_a_cpu(monkeypatch, tiny_sam3):
    from pipeline.teachers import sam3

    seen = []
    monkeypatch.setattr(sam3, "reuse_freed_memory", lambda device: seen.append("teacher"))
    sam3.Sam3Teacher(tiny_sam3, device="cpu", dtype="fp32", resolution=(40, 40)).load()
    assert seen == ["teacher"]
