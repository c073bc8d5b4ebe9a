"""The occupancy positives' yaw search and cell draw, and the streamed InfoNCE, on CUDA against the CPU (same inputs).

Run on a lent GPU by benchmarks/device_check/run.sh; prints one line per check.
"""
import torch
import torch.nn.functional as F

from threedq.contrastive import info_nce_plain, info_nce_streamed
from threedq.stages.positives import shape_agreement, shape_cells

dev = torch.device("cuda")  # the lent GPU (this script is the device check, not library code)
g = torch.Generator().manual_seed(0)
# smooth random blobs (not white noise) so that yaw ties are rare
x = torch.rand(256, 1, 8, 8, 8, generator=g)
occ = F.interpolate(x, size=(16, 16, 16), mode="trilinear", align_corners=False)
q, t = (occ[:128] > 0.5).float(), (occ[128:] > 0.5).float()
c0, y0 = shape_agreement(q, t, 36)
c1, y1 = shape_agreement(q.to(dev), t.to(dev), 36)
print(f"shape_agreement: max |cos cpu - cuda| {float((c0 - c1.cpu()).abs().max()):.2e}, "
      f"yaw equal {int((y0 == y1.cpu()).sum())}/{len(y0)}")
cells0, v0 = shape_cells(q, t, 8, torch.Generator().manual_seed(1))
cells1, v1 = shape_cells(q.to(dev), t.to(dev), 8, torch.Generator().manual_seed(1))
print(f"shape_cells: valid equal {torch.equal(v0, v1.cpu())}, cells equal {torch.equal(cells0, cells1.cpu())}, "
      f"device {cells1.device}")
qq = F.normalize(torch.randn(1024, 32, generator=g), dim=1)
kk = F.normalize(torch.randn(1024, 32, generator=g), dim=1)
qu = F.normalize(torch.randn(100000, 32, generator=g), dim=1)
a = info_nce_plain(qq.double(), kk.double(), qu.double(), 0.07)
b = info_nce_streamed(qq.to(dev), kk.to(dev), qu.to(dev), 0.07)
print(f"infonce streamed cuda fp32 vs plain cpu fp64: {abs(float(a) - float(b)):.2e}")
