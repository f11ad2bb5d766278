import time, torch, torch.nn.functional as F
torch.set_num_threads(2)
from pipeline.runtime.device import reuse_freed_memory; reuse_freed_memory("cpu")
torch.jit.enable_onednn_fusion(True)
def attn(q, k, v):
    s = torch.matmul(q, k.transpose(-1, -2)) * 0.17677669529663687
    p = torch.softmax(s, dim=-1)
    return torch.matmul(p, v)
def bench(f, n=5):
    ts=[]
    for _ in range(n):
        t0=time.perf_counter(); f(); ts.append(time.perf_counter()-t0)
    ts.sort(); return ts[n//2]*1e3
for shape in [(9,16,576,64), (6,8,5184,32)]:
    q,k,v = (torch.randn(*shape).to(torch.bfloat16) for _ in range(3))
    with torch.no_grad():
        tr = torch.jit.freeze(torch.jit.trace(attn, (q, k, v)).eval()) if False else torch.jit.trace(attn, (q, k, v))
        for _ in range(3): tr(q, k, v)
        ref = F.scaled_dot_product_attention(q, k, v)
        out = tr(q, k, v)
        print(shape, "max|diff| vs sdpa", (out.float()-ref.float()).abs().max().item())
        print(shape, "sdpa", round(bench(lambda: F.scaled_dot_product_attention(q, k, v)), 1), "ms; llga", round(bench(lambda: tr(q, k, v)), 1), "ms")
        print(tr.graph_for(q, k, v) if hasattr(tr, "graph_for") else "")
