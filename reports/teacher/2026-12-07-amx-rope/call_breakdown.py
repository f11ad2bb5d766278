import time, collections, numpy as np, torch, torch.nn.functional as F
torch.set_num_threads(2)
from pipeline.params import PAPER_PROMPTS as PROMPTS
from pipeline.teachers.base import TeacherInput
from pipeline.teachers import sam3
rng = np.random.default_rng(0)
items = [TeacherInput("img0", "sha0", rng.integers(0, 255, (256, 256, 3), dtype=np.uint8))]
t = sam3.Sam3Teacher("/work/amx/sam3-real", device="cpu", batch_size=1, resolution=(256, 256), score_threshold=0.0, dtype="auto")
m = t.load(); t.text_features(PROMPTS); t.predict(items, PROMPTS)
acc = collections.defaultdict(float); st = {}
for name, mod in m.named_modules():
    c = type(mod).__name__
    if c not in ("Linear", "LayerNorm", "Conv2d", "GroupNorm", "Sam3MLP", "Sam3DecoderMLP", "Sam3ViTLayer", "Sam3DetrEncoderLayer", "Sam3DetrDecoderLayer", "Sam3MaskDecoder", "Sam3DetrDecoder", "Sam3VisionNeck"): continue
    parts = name.split(".")
    key = f"{parts[0]}:{c}:{parts[-1] if c in ('Linear','LayerNorm','Conv2d') else ''}"
    if c == "Linear": key = f"{parts[0]}:Linear:{'.'.join(parts[-2:])}"
    def pre(mod, a, key=key): st[id(mod)] = time.perf_counter()
    def post(mod, a, o, key=key): acc[key] += time.perf_counter() - st.pop(id(mod))
    mod.register_forward_pre_hook(pre); mod.register_forward_hook(post)
sdpa = F.scaled_dot_product_attention
def timed_sdpa(q, k, v, *a, **kw):
    t0 = time.perf_counter(); o = sdpa(q, k, v, *a, **kw); acc[f"sdpa {tuple(q.shape)} kv{k.shape[-2]} mask={kw.get('attn_mask') is not None}"] += time.perf_counter() - t0; return o
F.scaled_dot_product_attention = timed_sdpa
torch.nn.functional.scaled_dot_product_attention = timed_sdpa
fits = sam3._patches_that_fit()
for i, p in enumerate(fits):
    f = p[2]
    def w(*a, f=f, n=p[1], **k):
        t0 = time.perf_counter(); o = f(*a, **k); acc["patch " + n] += time.perf_counter() - t0; return o
    fits[i] = (p[0], p[1], w)
for _ in range(2):
    acc.clear(); t0 = time.perf_counter(); t.predict(items, PROMPTS); w = time.perf_counter() - t0
    print(f"call {w:.2f}")
for k, v in sorted(acc.items(), key=lambda kv: -kv[1])[:45]:
    print(f"{v:7.3f}  {k}")
