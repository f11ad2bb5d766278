# sam3_old.py: git show dce4822:pipeline/teachers/sam3.py > sam3_old.py; usage: python old_vs_new_calls.py ROUNDS
import time, sys, hashlib, importlib.util, numpy as np, torch
torch.set_num_threads(2)
from pipeline.params import PAPER_PROMPTS as PROMPTS
from pipeline.teachers.base import TeacherInput
from pipeline.teachers import sam3
spec = importlib.util.spec_from_file_location("sam3_old", "sam3_old.py"); old = importlib.util.module_from_spec(spec); spec.loader.exec_module(old)
rng = np.random.default_rng(0)
items = [TeacherInput("img0", "sha0", rng.integers(0, 255, (256, 256, 3), dtype=np.uint8))]
t = sam3.Sam3Teacher("/work/amx/sam3-real", device="cpu", batch_size=1, resolution=(256, 256), score_threshold=0.0, dtype=sys.argv[2] if len(sys.argv) > 2 else "auto")
t.load(); t.text_features(PROMPTS)
fits = sam3._patches_that_fit()
new = list(fits); olds = [(o, n, getattr(old, r.__name__)) for o, n, r in new]
variants = {"old": olds, "new": new}
t.predict(items, PROMPTS)
res = {k: [] for k in variants}; out = {}
for r in range(int(sys.argv[1])):
    for k, v in variants.items():
        fits[:] = v
        t0 = time.perf_counter(); a = t.predict(items, PROMPTS); res[k].append(time.perf_counter() - t0); out[k] = a
print(t.path(), {k: [round(x, 2) for x in v] for k, v in res.items()}, {k: round(float(np.median(v)), 3) for k, v in res.items()})
for k, a in out.items():
    h = hashlib.sha256()
    for v in a: h.update(np.ascontiguousarray(np.asarray(v)).tobytes())
    print(k, h.hexdigest()[:16])
