#!/usr/bin/env python3
"""Would the classical coarse search see a part under a ramp of light? A measurement, not a matcher.

At each saved pair's true angle and scales, on the classical search's coarse level (the template
halved to 18x18 and both blurred by sigma 0.7, `matcher/classical.rs`), it maps the sparse 12x12
lattice's plain ZNCC and its plane-free correlation (a plane `a + b*u + c*v` fitted out of
template and samples alike) over every position, and reports where the truth's position ranks
among each map's local maxima (more than 9 coarse pixels away): `truth first` is the share of
pairs where no other place scores higher. Numpy and scipy; bilinear sampling as the search's.

Use it on tuning photos only, never on evaluation photos:

    posematch eval --images DIR --count 200 --level S1.5 --condition uneven-light --save /tmp/sv
    posematch match --pairs /tmp/sv/pairs.jsonl --out /tmp/sv/out.jsonl --max-instances 1
    python3 scripts/coarse-plane-probe.py /tmp/sv 7,12,21   # the ids lost, or "" for all
"""
import json, sys, math, numpy as np
from PIL import Image
from scipy.ndimage import gaussian_filter, map_coordinates, maximum_filter
d = sys.argv[1]
ids = set(sys.argv[2].split(',')) if len(sys.argv) > 2 and sys.argv[2] else None
def grey(p):
    a = np.asarray(Image.open(p).convert('RGB')).astype(np.float64) / 255
    return a[..., 0] * 0.299 + a[..., 1] * 0.587 + a[..., 2] * 0.114
def down(a):
    h, w = a.shape[0] // 2 * 2, a.shape[1] // 2 * 2
    a = a[:h, :w]; return (a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2]) / 4
res = {'zncc': [], 'plane-free': []}
for l in open(f"{d}/pairs.jsonl"):
    r = json.loads(l)
    if ids is not None and str(r['id']) not in ids: continue
    t = r['truth'][0]
    T = gaussian_filter(down(grey(f"{d}/{r['template']}")), 0.7)
    S = gaussian_filter(down(grey(f"{d}/{r['image']}")), 0.7)
    th, tw = T.shape
    g = np.linspace(0, tw - 1, 12); gv = np.linspace(0, th - 1, 12)
    U, V = np.meshgrid(g, gv); U = U.ravel(); V = V.ravel()
    w = map_coordinates(T, [V, U], order=1)
    u, v = U - (tw - 1) / 2, V - (th - 1) / 2
    a = math.radians(t['angle_deg']); sx, sy = t['scale_x'], t['scale_y']
    dx = sx * u * math.cos(a) + sy * v * math.sin(a); dy = -sx * u * math.sin(a) + sy * v * math.cos(a)
    H, W = S.shape
    Y, X = np.mgrid[0:H, 0:W]
    vals = np.stack([map_coordinates(S, [Y + dy[k], X + dx[k]], order=1, mode='nearest') for k in range(len(w))])  # n,H,W
    n = len(w)
    wz = w - w.mean()
    sm, sq, dot = vals.sum(0), (vals ** 2).sum(0), np.tensordot(wz, vals, 1)
    var = sq - sm ** 2 / n
    zn = dot / np.sqrt(np.maximum(var, 1e-12) * (wz ** 2).sum())
    # Detrended: both template weights and window values regressed on [1, u, v] (template coords).
    B = np.stack([np.ones(n), u, v], 1); Q, _ = np.linalg.qr(B)
    wd = wz - Q @ (Q.T @ wz)
    proj = np.tensordot(Q.T, vals, 1)  # 3,H,W
    vard = sq - (proj ** 2).sum(0)
    dn = np.tensordot(wd, vals, 1) / np.sqrt(np.maximum(vard, 1e-12) * (wd ** 2).sum())
    tx, ty = (t['x'] + 0.5) / 2 - 0.5, (t['y'] + 0.5) / 2 - 0.5
    for name, m in (('zncc', zn), ('plane-free', dn)):
        yy, xx = int(round(ty)), int(round(tx))
        at = m[max(0, yy - 1):yy + 2, max(0, xx - 1):xx + 2].max()
        peaks = (m == maximum_filter(m, size=9)) & (m > at)
        # peaks far from the truth
        far = peaks & ((X - tx) ** 2 + (Y - ty) ** 2 > 81)
        res[name].append((r['id'], at, int(far.sum())))
for name, v in res.items():
    ranks = np.array([x[2] for x in v]); ats = np.array([x[1] for x in v])
    print(name, 'truth first', (ranks == 0).mean().round(3), 'top4', (ranks < 4).mean().round(3), 'top20', (ranks < 20).mean().round(3), 'median score at truth', np.median(ats).round(3))
if ids is not None:
    for a, b in zip(res['zncc'], res['plane-free']): print(a[0], 'zncc %.3f rank %d | plane-free %.3f rank %d' % (a[1], a[2], b[1], b[2]))
