import torch
from transformers.models.sam3.modeling_sam3 import apply_rotary_pos_emb_2d as ref
def rope_complex(q, k, cos, sin):
    fc = torch.complex(cos[..., 0::2].float(), sin[..., 0::2].float())
    def rot(x):
        xf = x.to(torch.float32, copy=True)
        torch.view_as_complex(xf.unflatten(-1, (-1, 2))).mul_(fc)
        return xf.type_as(x)
    return rot(q), rot(k)
g = torch.Generator().manual_seed(1)
bad = 0
for (B,N,H,D) in [(2,16,2,8),(3,9,4,4),(1,25,2,6),(2,49,3,16),(1,7,1,2),(4,64,2,32)]:
    cos = torch.randn(1,N,D//2, generator=g).repeat_interleave(2,-1); sin = torch.randn(1,N,D//2, generator=g).repeat_interleave(2,-1)
    for dt in (torch.float32, torch.bfloat16):
        for _ in range(20):
            x = (torch.randn(B,N,H*D, generator=g)*10).to(dt); y = torch.randn(B,N,H*D, generator=g).to(dt)
            q = x.view(B,N,H,D).transpose(1,2); k = y.view(B,N,H,D).transpose(1,2)
            a = rope_complex(q,k,cos,sin); b = ref(q,k,cos,sin)
            iv = torch.int16 if dt == torch.bfloat16 else torch.int32
            if not all(torch.equal(u.view(iv), v.view(iv)) for u,v in zip(a,b)):
                bad += 1; print("DIFF", (B,N,H,D), dt, max((u.float()-v.float()).abs().max().item() for u,v in zip(a,b)))
print("bad", bad)
