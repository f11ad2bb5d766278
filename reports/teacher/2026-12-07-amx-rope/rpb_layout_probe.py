import time, torch
torch.set_num_threads(2)
from pipeline.runtime.device import reuse_freed_memory; reuse_freed_memory("cpu")
B,Q,R,C,Hh = 6,200,72,72,8
dy = torch.randn(B,Q,R,Hh).to(torch.bfloat16); dx = torch.randn(B,Q,C,Hh).to(torch.bfloat16)
def cur():
    out = torch.empty(B,Hh,Q,R*C, dtype=torch.bfloat16)
    torch.add(dy.unsqueeze(3), dx.unsqueeze(2), out=out.view(B,Hh,Q,R,C).permute(0,2,3,4,1)); return out
def headsmajor():
    out = torch.empty(B,Hh,Q,R*C, dtype=torch.bfloat16)
    y = dy.permute(0,3,1,2).contiguous(); x = dx.permute(0,3,1,2).contiguous()
    torch.add(y.unsqueeze(-1), x.unsqueeze(-2), out=out.view(B,Hh,Q,R,C)); return out
def padded():
    out = torch.empty(B,Hh,Q+1,R*C, dtype=torch.bfloat16); out[:,:,0].zero_()
    y = dy.permute(0,3,1,2).contiguous(); x = dx.permute(0,3,1,2).contiguous()
    torch.add(y.unsqueeze(-1), x.unsqueeze(-2), out=out[:,:,1:].view(B,Hh,Q,R,C)); return out
import torch.nn.functional as F
a = cur(); b = headsmajor(); c = padded()
print(torch.equal(a.view(torch.int16), b.view(torch.int16)), torch.equal(F.pad(a,(0,0,1,0)).view(torch.int16), c.view(torch.int16)))
for name, f in (("cur", cur), ("headsmajor", headsmajor), ("padded", padded), ("cur+pad", lambda: F.pad(cur(), (0,0,1,0)))):
    ts=[]
    for _ in range(7):
        t0=time.perf_counter(); f(); ts.append(time.perf_counter()-t0)
    ts.sort(); print(name, f"{ts[3]*1e3:.1f} ms")
