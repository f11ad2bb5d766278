import time, torch, torch.nn.functional as F
torch.set_num_threads(2)
from pipeline.runtime.device import reuse_freed_memory; reuse_freed_memory("cpu")
def bench(f, n=5):
    f(); ts=[]
    for _ in range(n):
        t0=time.perf_counter(); f(); ts.append(time.perf_counter()-t0)
    ts.sort(); return ts[n//2]*1e3
for (B,H,N,D) in [(6,8,5184,32),(1,16,5184,64),(9,16,576,64)]:
    for dt in (torch.bfloat16, torch.float32):
        q,k,v = (torch.randn(B,N,H,D).to(dt).transpose(1,2) for _ in range(3))
        fl = 4*B*H*N*N*D
        ms = bench(lambda: F.scaled_dot_product_attention(q,k,v))
        print((B,H,N,D), dt, f"sdpa {ms:.1f} ms {fl/ms/1e6:.0f} GFLOP/s")
    qc,kc = (torch.randn(B*H,N,D).to(torch.bfloat16) for _ in range(2))
    ms = bench(lambda: torch.bmm(qc[:, :512], kc.transpose(1,2)))
    print("  qk^T bf16 bmm (512 q rows)", f"{ms:.1f} ms -> full {ms*N/512:.0f} ms, {2*B*H*512*N*D/ms/1e6:.0f} GFLOP/s")
    s = torch.randn(B*H, 512, N)
    ms = bench(lambda: torch.softmax(s, -1))
    print("  softmax fp32 (512 rows)", f"{ms:.1f} ms -> full {ms*N/512:.0f} ms")
    ms = bench(lambda: torch.exp(s))
    print("  exp fp32 (512 rows)", f"{ms:.1f} ms -> full {ms*N/512:.0f} ms")
