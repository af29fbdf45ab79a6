#!/usr/bin/env python3
"""Classical baseline: tuned, masked, coarse-to-fine OpenCV NCC template matcher.

Finds a template in an image under rotation (full circle) and anisotropic scale
(independent scale_x / scale_y) and writes poses in PoseMatch's public pose
convention.  Needs only python3, numpy and opencv-python-headless
(``python3 -m pip install opencv-python-headless numpy``).

Usage
-----
    python3 scripts/opencv_ncc.py --pairs DIR/pairs.jsonl --out results.jsonl \
        [--max-instances N] [--min-score S] [--scale-range LO,HI] [--threads T]

Each input line is ``{"id": .., "image": .., "template": .., ...}`` with paths
relative to the folder of ``pairs.jsonl``.  Any ``truth`` field is ignored: it
is never read by the matcher.  Each output line, in input order, is

    {"id": <id>, "poses": [{"x", "y", "angle_deg", "scale_x", "scale_y",
                            "score"}, ...], "ms": <float>}

with poses best first.  ``ms`` is the wall-clock time of matching one pair:
it EXCLUDES reading and decoding the two PNG files (cv2.imread, done in
greyscale) and INCLUDES everything after (float conversion, pyramid, template
variants, search, refinement).

Pose convention (PoseMatch public contract)
-------------------------------------------
A template pixel offset (u, v) from the template centre (u right, v down) maps
to the image point

    (x + sx*u*cos a + sy*v*sin a,  y - sx*u*sin a + sy*v*cos a),

a = radians(angle_deg).  Positive angles turn counter-clockwise on screen
(like cv2.getRotationMatrix2D with a positive angle); angle_deg lies in
(-180, 180].  scale_x / scale_y = object width / height in the image divided by
the template width / height.  Pixel centres are integers: the top-left pixel's
centre is (0, 0) and the template centre is ((w-1)/2, (h-1)/2).

Score: the masked zero-mean NCC (cv2.TM_CCOEFF_NORMED with a mask, i.e. the
Pearson correlation over the pixels covered by the warped template), clipped
to [0, 1]: score = min(1, max(0, ncc)).  Anti-correlation counts as 0.
PoseMatch's score is calibrated differently (the ZNCC measured against what an
unrelated patch reaches by chance; docs/accuracy.md "What a score means"), so the same
--min-score does not mean the same thing for both matchers.

Method
------
Images and templates are read as 8-bit grey (cv2.IMREAD_GRAYSCALE) and
converted to float32.

1. Template variants.  For an (angle, sx, sy) the template is warped with
   cv2.warpAffine (bilinear, replicated border) onto the smallest odd-sized
   canvas that holds the rotated, scaled template, its centre on a canvas pixel
   centre (plus an optional sub-pixel offset).  A mask of the pixels inside the
   warped template is warped the same way; only fully covered pixels are valid
   (coverage >= --mask-threshold).  Similarity is the masked NCC
   ``cv2.matchTemplate(image, variant, cv2.TM_CCOEFF_NORMED, mask=mask)``;
   NaN/inf (flat image patches) are set to -1.

2. Coarse exhaustive search.  The image is reduced with cv2.pyrDown to the
   deepest level at which the template's smaller side, at scale LO, is still
   >= --coarse-size px (level 1, 18 px, for 36 px templates).  Coarse variants
   are warped at full resolution and reduced by the same pyrDown chain, so they
   look like the reduced image.  Angles: the whole circle, start 0, in steps of
   --angle-step deg (default: --angle-factor * 2*atan(1/r), r = the template's
   half diagonal at the coarse level and the mean scale: 12.3 deg (30 angles)
   for 36 px templates and range 0.8..1.5, 13.5 deg (27 angles) at scale 1).
   Scales: every (sx, sy) pair of a geometric grid over --scale-range with
   relative step <= --scale-step (0.8, 0.99, 1.22, 1.5 by default; only LO when
   LO == HI).  The image is padded by --pad px (replicated) so objects touching
   the border are found.  For each position the best score over all variants
   (and which variant) is kept; local maxima of this map with greedy NMS by
   centre distance give the --candidates best hypotheses (or
   --candidates-per-instance * --max-instances if more).

3. Full-resolution refinement, per hypothesis: a pattern search over
   (angle, log sx, log sy).  Each evaluation scores one variant on a
   (2*--fine-radius+1)^2 grid of centres around the current sub-pixel position
   (the template is warped with the fractional offset) and returns the
   parabola-interpolated peak value and position, so angles and scales are
   compared at their own best sub-pixel positions.  Steps start at half the
   coarse steps; +-step along each axis is tried first, then the combined
   (diagonal) moves; the best improving move is taken; otherwise the steps
   halve, down to --min-angle-step deg and --min-scale-step (log scale).
   Scales may leave the range by --scale-slack (log).  The search runs in two
   phases: all hypotheses to a quarter of the coarse steps, then hypotheses
   more than --prune-margin below the best (only once --max-instances are
   kept) or below --min-score - --prune-margin are dropped, as are duplicates,
   and the rest are searched to the end.

4. Sub-pixel: angle and each scale by a parabola through the best value and its
   neighbours at the last step; the position by separable parabolas through
   the 3x3 correlation neighbourhood of the final pose.  The reported score is
   the masked NCC sample nearest the final pose.

5. Output: refined poses, best first, NMS by centre distance (--nms-factor x
   the smaller template side x the smaller scale of the two poses), scores
   below --min-score and centres off the image dropped, at most
   --max-instances.

Threads: cv2.setNumThreads(--threads), and the coarse variants and the
hypotheses are spread over a pool of --threads Python threads (OpenCV releases
the GIL in matchTemplate).

Defaults were tuned only on separate tuning pairs (36x36 templates; 224x224
single-object images at scale 1 and at scales 0.8..1.5 per axis; 320x320
multi-object scenes), never on the evaluation pairs.  Coarser or finer coarse
grids trade speed for robustness; on the 100 tuning pairs at scales 0.8..1.5
(2-core machine, busy): --angle-factor 2.5 --scale-step 0.25: 98 % at
~270 ms/pair; the defaults (1.5, 0.25): 99 % at ~360 ms/pair;
--angle-factor 1.0 --scale-step 0.1: 99 % at ~1650 ms/pair.
"""

import argparse
import json
import math
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np


# ---------------------------------------------------------------- variants --

def make_variant(tmpl, angle_deg, sx, sy, level, mask_threshold, ox=0.0, oy=0.0):
    """Warp the template for (angle, sx, sy) and reduce it `level` times.

    The template centre lands at canvas pixel (ccx + ox, ccy + oy) (full-resolution
    offsets, |ox|, |oy| <= 0.5).  Returns (variant, mask, ccx, ccy): the canvas and
    mask at the pyramid level and the integer part of the centre there."""
    h, w = tmpl.shape
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    # half extents of the warped template box (pixel edges), full resolution
    hx = abs(sx * c) * w / 2.0 + abs(sy * s) * h / 2.0
    hy = abs(sx * s) * w / 2.0 + abs(sy * c) * h / 2.0
    step = 1 << level
    big_x = int(math.ceil((hx + 0.5) / step)) * step
    big_y = int(math.ceil((hy + 0.5) / step)) * step
    cw, ch = 2 * big_x + 1, 2 * big_y + 1
    m = np.array([[sx * c, sy * s, big_x + ox - sx * c * cx - sy * s * cy],
                  [-sx * s, sy * c, big_y + oy + sx * s * cx - sy * c * cy]], np.float64)
    var = cv2.warpAffine(tmpl, m, (cw, ch), flags=cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)
    msk = cv2.warpAffine(np.ones_like(tmpl), m, (cw, ch), flags=cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    for _ in range(level):
        var = cv2.pyrDown(var)
        msk = cv2.pyrDown(msk)
    msk = (msk >= mask_threshold).astype(np.float32)
    return var, msk, big_x >> level, big_y >> level


def masked_ncc(image, var, msk):
    r = cv2.matchTemplate(image, var, cv2.TM_CCOEFF_NORMED, mask=msk)
    r[~np.isfinite(r)] = -1.0
    return r


def wrap_angle(a):
    """Wrap degrees to (-180, 180]."""
    a = math.fmod(a, 360.0)
    if a <= -180.0:
        a += 360.0
    elif a > 180.0:
        a -= 360.0
    return a


def scale_grid(lo, hi, rel_step):
    if hi <= lo * (1 + 1e-6):
        return [lo]
    n = max(2, int(math.ceil(math.log(hi / lo) / math.log(1.0 + rel_step))) + 1)
    return [lo * (hi / lo) ** (i / (n - 1)) for i in range(n)]


def parabola_peak(fm, f0, fp):
    """Vertex of the parabola through (-1, fm), (0, f0), (1, fp): (offset in steps,
    clipped to [-0.5, 0.5], and the value gained over f0)."""
    fm, f0, fp = float(fm), float(f0), float(fp)
    den = fm - 2.0 * f0 + fp
    if den >= 0 or not all(map(math.isfinite, (fm, f0, fp))):
        return 0.0, 0.0
    t = min(0.5, max(-0.5, 0.5 * (fm - fp) / den))
    return t, 0.5 * (fp - fm) * t + 0.5 * den * t * t


# ----------------------------------------------------------------- matcher --

class Matcher:
    def __init__(self, args):
        self.a = args

    # -- coarse ---------------------------------------------------------------
    def coarse(self, tmpl, img_c, level, angles, scales, pool, n_cand, nms_c):
        a = self.a
        H, W = img_c.shape
        pad = a.pad
        img_p = cv2.copyMakeBorder(img_c, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
        variants = [(ang, sx, sy) for ang in angles for sx in scales for sy in scales]

        def work(chunk):
            best = np.full((H, W), -2.0, np.float32)
            idx = np.full((H, W), -1, np.int32)
            for vi in chunk:
                ang, sx, sy = variants[vi]
                var, msk, ccx, ccy = make_variant(tmpl, ang, sx, sy, level, a.mask_threshold)
                if var.shape[0] > img_p.shape[0] or var.shape[1] > img_p.shape[1]:
                    continue
                r = masked_ncc(img_p, var, msk)
                # r[i, j] -> centre (j + ccx - pad, i + ccy - pad) in img_c
                x0, y0 = ccx - pad, ccy - pad
                rx0, ry0 = max(0, -x0), max(0, -y0)
                bx0, by0 = x0 + rx0, y0 + ry0
                bw = min(W - bx0, r.shape[1] - rx0)
                bh = min(H - by0, r.shape[0] - ry0)
                if bw <= 0 or bh <= 0:
                    continue
                rr = r[ry0:ry0 + bh, rx0:rx0 + bw]
                bb = best[by0:by0 + bh, bx0:bx0 + bw]
                ii = idx[by0:by0 + bh, bx0:bx0 + bw]
                upd = rr > bb
                bb[upd] = rr[upd]
                ii[upd] = vi
            return best, idx

        nt = max(1, a.threads)
        order = list(range(len(variants)))
        chunks = [order[k::nt] for k in range(nt)]
        if pool is not None and nt > 1:
            parts = list(pool.map(work, chunks))
        else:
            parts = [work(c) for c in chunks]
        best, idx = parts[0]
        for b2, i2 in parts[1:]:
            upd = b2 > best
            best[upd] = b2[upd]
            idx[upd] = i2[upd]

        # 3x3 local maxima, then greedy NMS on centre distance
        dil = cv2.dilate(best, np.ones((3, 3), np.uint8))
        ys, xs = np.nonzero((best >= dil) & (idx >= 0) & (best > -1.5))
        vals = best[ys, xs]
        order = np.argsort(-vals)
        picked = []
        for o in order:
            y, x = int(ys[o]), int(xs[o])
            if all((x - px) ** 2 + (y - py) ** 2 >= nms_c ** 2 for px, py, _, _ in picked):
                picked.append((x, y, float(vals[o]), variants[idx[y, x]]))
                if len(picked) >= n_cand:
                    break
        return picked

    # -- fine -----------------------------------------------------------------
    def evaluate(self, tmpl, img_p, pad, ang, sx, sy, x, y, r):
        """Masked NCC on the grid of centres (x + i, y + j), |i|, |j| <= r.

        (x, y) may be fractional: the template is warped with the fractional
        part, so the grid is centred exactly on (x, y).  Returns
        (peak, x', y', sample, res): the parabola-interpolated peak value and
        position around the best grid sample, that sample's NCC, and the map."""
        xb, yb = int(math.floor(x + 0.5)), int(math.floor(y + 0.5))
        fx, fy = x - xb, y - yb
        var, msk, ccx, ccy = make_variant(tmpl, ang, sx, sy, 0, self.a.mask_threshold,
                                          fx, fy)
        ch, cw = var.shape
        # region of the padded image whose matchTemplate result covers the grid
        x0 = xb - r - ccx + pad
        y0 = yb - r - ccy + pad
        x1 = x0 + cw + 2 * r
        y1 = y0 + ch + 2 * r
        if x0 < 0 or y0 < 0 or x1 > img_p.shape[1] or y1 > img_p.shape[0]:
            return -2.0, x, y, -2.0, None
        res = masked_ncc(img_p[y0:y1, x0:x1], var, msk)
        _, mx, _, (i, j) = cv2.minMaxLoc(res)
        peak, dx, dy = float(mx), 0.0, 0.0
        if 0 < i < res.shape[1] - 1:
            dx, g = parabola_peak(res[j, i - 1], mx, res[j, i + 1])
            peak += g
        if 0 < j < res.shape[0] - 1:
            dy, g = parabola_peak(res[j - 1, i], mx, res[j + 1, i])
            peak += g
        return peak, x - r + i + dx, y - r + j + dy, float(mx), res

    def ev(self, ctx, p, x, y, r):
        tmpl, img_p, pad = ctx["tmpl"], ctx["img_p"], ctx["pad"]
        return self.evaluate(tmpl, img_p, pad, p[0], math.exp(p[1]), math.exp(p[2]), x, y, r)

    def start(self, ctx, cand):
        """Full-resolution hypothesis from a coarse candidate."""
        xc_c, yc_c, _, (ang, sx, sy) = cand
        step = ctx["step"]
        cur = [ang, math.log(sx), math.log(sy)]
        sc, x, y, _, _ = self.ev(ctx, cur, xc_c * step, yc_c * step, step + 1)
        return {"cur": cur, "sc": sc, "x": x, "y": y,
                "da": ctx["coarse_da"] / 2.0, "ds": ctx["coarse_ds"] / 2.0}

    def search(self, ctx, st, min_da, min_ds):
        """Pattern search over (angle, log sx, log sy) at full resolution until the steps
        are <= (min_da, min_ds).  Axis moves first, then combined (diagonal) moves, then
        the steps halve.  The position follows each evaluation's interpolated peak."""
        a = self.a
        fixed_scale = ctx["fixed_scale"]
        ls_lo, ls_hi = ctx["ls_lo"], ctx["ls_hi"]
        cur, sc, x, y, da, ds = st["cur"], st["sc"], st["x"], st["y"], st["da"], st["ds"]
        it = 0
        while it < a.max_iters:
            it += 1
            best = None
            for group in ctx["moves"]:
                for k0, k1, k2 in group:
                    p = [cur[0] + k0 * da, cur[1] + k1 * ds, cur[2] + k2 * ds]
                    if not (ls_lo <= p[1] <= ls_hi and ls_lo <= p[2] <= ls_hi):
                        continue
                    s2, x2, y2, _, _ = self.ev(ctx, p, x, y, a.fine_radius)
                    if s2 > sc + 1e-6 and (best is None or s2 > best[0]):
                        best = (s2, x2, y2, p)
                if best is not None:
                    break
            if best is not None:
                sc, x, y, cur = best
                continue
            da_small = da <= min_da * (1 + 1e-9)
            ds_small = fixed_scale or ds <= min_ds * (1 + 1e-9)
            if da_small and ds_small:
                break
            if not da_small:
                da /= 2.0
            if not ds_small:
                ds /= 2.0
        st.update(cur=cur, sc=sc, x=x, y=y, da=da, ds=ds)
        return st

    def finish(self, ctx, st):
        """Sub-pixel angle / scales (parabola through the best value and its neighbours
        at the last step), final position and score; returns the pose dict."""
        cur, sc, x, y, da, ds = st["cur"], st["sc"], st["x"], st["y"], st["da"], st["ds"]
        out = list(cur)
        dims = [(0, da)] + ([] if ctx["fixed_scale"] else [(1, ds), (2, ds)])
        for dim, dv in dims:
            vals = []
            for sgn in (-1, 1):
                p = list(cur)
                p[dim] += sgn * dv
                vals.append(self.ev(ctx, p, x, y, 1)[0])
            out[dim] = cur[dim] + dv * parabola_peak(vals[0], sc, vals[1])[0]
        # final position (grid centred on the estimate) and score at the final pose
        pk, x2, y2, sample, _ = self.ev(ctx, out, x, y, 1)
        if pk >= sc - 1e-3:
            x, y = x2, y2
        else:  # the parabolas made it worse: keep the searched pose
            out = cur
            pk, x, y, sample, _ = self.ev(ctx, out, x, y, 1)
        return {
            "x": x,
            "y": y,
            "angle_deg": wrap_angle(out[0]),
            "scale_x": math.exp(out[1]),
            "scale_y": math.exp(out[2]),
            "score": float(min(1.0, max(0.0, sample))),
        }

    # -- one pair -------------------------------------------------------------
    def match(self, tmpl_u8, img_u8, pool):
        a = self.a
        tmpl = tmpl_u8.astype(np.float32)
        img = img_u8.astype(np.float32)
        th, tw = tmpl.shape
        s_lo, s_hi = a.scale_range

        # pyramid level: largest with the template's smaller side >= coarse_size
        level = a.level
        if level < 0:
            level = 0
            while min(th, tw) * s_lo / (2 ** (level + 1)) >= a.coarse_size and \
                    min(img.shape) / (2 ** (level + 1)) >= 2 * max(th, tw) * s_hi / (2 ** (level + 1)):
                level += 1
        pyr = [img]
        for _ in range(level):
            pyr.append(cv2.pyrDown(pyr[-1]))
        img_c = pyr[level]
        step = 1 << level

        r_c = 0.5 * math.hypot(tw, th) * math.sqrt(s_lo * s_hi) / step
        da = a.angle_step if a.angle_step > 0 else \
            a.angle_factor * 2.0 * math.degrees(math.atan(1.0 / r_c))
        n_ang = max(1, int(math.ceil(360.0 / da - 1e-9)))
        da = 360.0 / n_ang
        angles = [wrap_angle(i * da) for i in range(n_ang)]
        scales = scale_grid(s_lo, s_hi, a.scale_step)
        ds = math.log(scales[1] / scales[0]) if len(scales) > 1 else 0.0

        n_cand = max(a.candidates, a.candidates_per_instance * a.max_instances)
        nms_c = a.nms_factor * min(th, tw) * s_lo / step
        cands = self.coarse(tmpl, img_c, level, angles, scales, pool, n_cand, nms_c)

        pad = int(math.ceil(math.hypot(tw, th) * s_hi * 0.5)) + 8
        fixed_scale = len(scales) == 1
        axis = [(1.0, 0.0, 0.0), (-1.0, 0.0, 0.0)]
        if not fixed_scale:
            axis += [(0.0, 1.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, 1.0), (0.0, 0.0, -1.0)]
        diag = []
        if a.diagonal:
            rng = (-1.0, 0.0, 1.0)
            srng = rng if not fixed_scale else (0.0,)
            diag = [(k0, k1, k2) for k0 in rng for k1 in srng for k2 in srng
                    if (k0 != 0) + (k1 != 0) + (k2 != 0) >= 2]
        ctx = {
            "tmpl": tmpl, "pad": pad, "step": step,
            "img_p": cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_REPLICATE),
            "coarse_da": da, "coarse_ds": ds, "fixed_scale": fixed_scale,
            "ls_lo": math.log(s_lo) - a.scale_slack, "ls_hi": math.log(s_hi) + a.scale_slack,
            "moves": [axis, diag],
        }

        def run(fn, items):
            if pool is not None and a.threads > 1 and len(items) > 1:
                return list(pool.map(fn, items))
            return [fn(i) for i in items]

        # phase 1: every hypothesis down to a quarter of the coarse steps
        sts = run(lambda c: self.search(ctx, self.start(ctx, c), da / 4.0, ds / 4.0), cands)
        # prune hopeless and duplicate hypotheses, then phase 2 on the rest
        sts.sort(key=lambda st: -st["sc"])
        top = sts[0]["sc"] if sts else 0.0
        keep = []
        for st in sts:
            if st["sc"] < a.min_score - a.prune_margin:
                break
            if len(keep) >= a.max_instances and st["sc"] < top - a.prune_margin:
                break
            d = a.nms_factor * min(th, tw) * math.exp(min(st["cur"][1], st["cur"][2]))
            if any((st["x"] - q["x"]) ** 2 + (st["y"] - q["y"]) ** 2 < d * d for q in keep):
                continue
            keep.append(st)
        poses = run(lambda st: self.finish(ctx, self.search(ctx, st, a.min_angle_step,
                                                                 a.min_scale_step)), keep)

        poses.sort(key=lambda p: -p["score"])
        kept = []
        for p in poses:
            if p["score"] < a.min_score:
                continue
            if not (-0.5 <= p["x"] <= img.shape[1] - 0.5 and -0.5 <= p["y"] <= img.shape[0] - 0.5):
                continue  # the centre drifted off the image
            ok = True
            for q in kept:
                d = a.nms_factor * min(th, tw) * min(p["scale_x"], p["scale_y"],
                                                    q["scale_x"], q["scale_y"])
                if (p["x"] - q["x"]) ** 2 + (p["y"] - q["y"]) ** 2 < d * d:
                    ok = False
                    break
            if ok:
                kept.append(p)
                if len(kept) >= a.max_instances:
                    break
        return kept


# -------------------------------------------------------------------- main --

def parse_range(s):
    lo, hi = (float(v) for v in s.split(","))
    if lo <= 0 or hi < lo:
        raise argparse.ArgumentTypeError("scale range must be LO,HI with 0 < LO <= HI")
    return lo, hi


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--pairs", required=True, help="pairs.jsonl")
    p.add_argument("--out", required=True, help="output jsonl")
    p.add_argument("--max-instances", type=int, default=1)
    p.add_argument("--min-score", type=float, default=0.0)
    p.add_argument("--scale-range", type=parse_range, default=(0.8, 1.5),
                   help="LO,HI searched for both scale_x and scale_y (default 0.8,1.5; "
                        "1,1 searches scale 1 only)")
    p.add_argument("--threads", type=int, default=2)
    # tuning knobs
    p.add_argument("--coarse-size", type=float, default=12.0,
                   help="smallest template side (px, at scale LO) wanted at the coarse level")
    p.add_argument("--level", type=int, default=-1, help="coarse pyramid level (-1: auto)")
    p.add_argument("--angle-step", type=float, default=0.0,
                   help="coarse angle step in degrees (0: auto from template radius)")
    p.add_argument("--angle-factor", type=float, default=1.5,
                   help="multiplier of the auto angle step 2*atan(1/r)")
    p.add_argument("--scale-step", type=float, default=0.25,
                   help="relative step of the coarse scale grid")
    p.add_argument("--candidates", type=int, default=6,
                   help="coarse hypotheses refined (single instance)")
    p.add_argument("--candidates-per-instance", type=int, default=3)
    p.add_argument("--nms-factor", type=float, default=0.75,
                   help="NMS centre distance, in smaller template sides (times the smaller "
                        "scale)")
    p.add_argument("--mask-threshold", type=float, default=0.999)
    p.add_argument("--pad", type=int, default=1, help="coarse image border (px) searched")
    p.add_argument("--fine-radius", type=int, default=2)
    p.add_argument("--min-angle-step", type=float, default=0.25)
    p.add_argument("--min-scale-step", type=float, default=0.004)
    p.add_argument("--scale-slack", type=float, default=0.03,
                   help="log-scale margin the refinement may go past the range")
    p.add_argument("--max-iters", type=int, default=60)
    p.add_argument("--prune-margin", type=float, default=0.1,
                   help="after the first refinement phase, drop hypotheses scoring this much "
                        "below the best (or below --min-score)")
    p.add_argument("--diagonal", type=int, default=1,
                   help="1: try combined angle/scale moves before halving the steps")
    p.add_argument("--limit", type=int, default=0, help="only the first N pairs (0: all)")
    args = p.parse_args(argv)

    cv2.setNumThreads(max(1, args.threads))
    folder = os.path.dirname(os.path.abspath(args.pairs))
    matcher = Matcher(args)
    pool = ThreadPoolExecutor(args.threads) if args.threads > 1 else None
    n = 0
    with open(args.pairs) as fin, open(args.out, "w") as fout:
        for line in fin:
            line = line.strip()
            if not line:
                continue
            pair = json.loads(line)
            img = cv2.imread(os.path.join(folder, pair["image"]), cv2.IMREAD_GRAYSCALE)
            tmpl = cv2.imread(os.path.join(folder, pair["template"]), cv2.IMREAD_GRAYSCALE)
            if img is None or tmpl is None:
                print(f"pair {pair.get('id')}: cannot read images", file=sys.stderr)
                poses, ms = [], 0.0
            else:
                t0 = time.perf_counter()
                poses = matcher.match(tmpl, img, pool)
                ms = (time.perf_counter() - t0) * 1000.0
            fout.write(json.dumps({"id": pair["id"], "poses": poses, "ms": round(ms, 3)}) + "\n")
            fout.flush()
            n += 1
            if args.limit and n >= args.limit:
                break
    if pool is not None:
        pool.shutdown()


if __name__ == "__main__":
    main()
