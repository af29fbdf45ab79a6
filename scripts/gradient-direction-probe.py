#!/usr/bin/env python3
"""Would a gradient-direction reading find the parts the score loses? A measurement, not a matcher.

Shape-based matchers (Halcon, PatMax, line2Dup) score the mean cosine between the model's
gradient directions at its edge points and the image's there. This reads that cosine at the
answers PoseMatch gave for saved pairs and, per template, compares the part with the best
answer in the same scene without the part: whether the reading orders the part above that
template's best look-alike more often than the score does, and how many scenes without the part
have a look-alike reading at least as high as each part the score loses.

Use it on tuning photos only, never on evaluation photos:

    for c in jpeg-30 absent,jpeg-30; do
      posematch eval --images DIR --count 200 --level S1.5 --condition $c --save /tmp/sv-$c
      posematch match --pairs /tmp/sv-$c/pairs.jsonl --out /tmp/sv-$c/out.jsonl \\
          --min-score 0.001 --max-instances 3
    done
    python3 scripts/gradient-direction-probe.py /tmp/sv-jpeg-30 /tmp/sv-absent,jpeg-30

Edge points: the template's strongest 30 % of gradients (Gaussian derivatives, sigma 1 px); the
image's gradients at sigma 1 px times the part's scale; directions mapped through the pose's
linear part (inverse transpose), as the README's pose convention defines it.
"""

import argparse
import json
from pathlib import Path

import numpy as np
from PIL import Image
from scipy import ndimage

EDGE_SHARE = 0.3
SIGMA = 1.0


def gray(path):
    rgb = np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0
    return rgb @ np.array([0.299, 0.587, 0.114], dtype=np.float32)


def gradients(image, sigma):
    return (ndimage.gaussian_filter(image, sigma, order=(0, 1)),
            ndimage.gaussian_filter(image, sigma, order=(1, 0)))


def edge_points(template):
    """Offsets from the template centre and unit gradient directions of its strongest edges."""
    gx, gy = gradients(template, SIGMA)
    magnitude = np.hypot(gx, gy)
    h, w = template.shape
    ys, xs = np.mgrid[0:h, 0:w]
    inner = (xs >= 1) & (xs < w - 1) & (ys >= 1) & (ys < h - 1)
    chosen = inner & (magnitude >= np.quantile(magnitude[inner], 1 - EDGE_SHARE)) & (magnitude > 1e-4)
    directions = np.stack([gx[chosen], gy[chosen]], 1) / magnitude[chosen][:, None]
    return xs[chosen] - (w - 1) / 2, ys[chosen] - (h - 1) / 2, directions


def direction_reading(image, pose, points):
    """Mean cosine between the mapped template directions and the image's at `pose`."""
    u, v, directions = points
    gx, gy = gradients(image, SIGMA * np.sqrt(pose["scale_x"] * pose["scale_y"]))
    a = np.radians(pose["angle_deg"])
    linear = np.array([[pose["scale_x"] * np.cos(a), pose["scale_y"] * np.sin(a)],
                       [-pose["scale_x"] * np.sin(a), pose["scale_y"] * np.cos(a)]])
    px = pose["x"] + linear[0, 0] * u + linear[0, 1] * v
    py = pose["y"] + linear[1, 0] * u + linear[1, 1] * v
    expected = directions @ np.linalg.inv(linear)
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    ix = ndimage.map_coordinates(gx, [py, px], order=1, mode="nearest")
    iy = ndimage.map_coordinates(gy, [py, px], order=1, mode="nearest")
    magnitude = np.hypot(ix, iy)
    cosine = (expected[:, 0] * ix + expected[:, 1] * iy) / np.maximum(magnitude, 1e-6)
    cosine[magnitude < 1e-4] = 0.0
    return float(cosine.mean())


def right(pose, truth):
    turn = (pose["angle_deg"] - truth["angle_deg"] + 180) % 360 - 180
    return np.hypot(pose["x"] - truth["x"], pose["y"] - truth["y"]) < 3 and abs(turn) < 5


def best_answers(folder):
    """Per pair id: (best answer's score, its direction reading, whether it is the part)."""
    pairs = {p["id"]: p for p in map(json.loads, (folder / "pairs.jsonl").open())}
    answers = {a["id"]: a for a in map(json.loads, (folder / "out.jsonl").open())}
    out = {}
    for i, pair in pairs.items():
        poses = answers.get(i, {}).get("poses") or []
        if not poses:
            continue
        best = poses[0]
        points = edge_points(gray(folder / pair["template"]))
        reading = direction_reading(gray(folder / pair["image"]), best, points)
        out[i] = (best["score"], reading, right(best, pair["truth"][0]))
    return out


parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("present", type=Path, help="saved pairs with the part, with out.jsonl")
parser.add_argument("absent", type=Path, help="the same pairs' scenes without the part")
args = parser.parse_args()

present, absent = best_answers(args.present), best_answers(args.absent)
lost = sorted(i for i, (score, _, ok) in present.items() if ok and score < 0.9)
look_alikes = [absent[i] for i in absent if absent[i][0] < 0.9]  # copies of the part score higher
scores = np.array([s for s, _, _ in look_alikes])
readings = np.array([r for _, r, _ in look_alikes])
print(f"{len(lost)} parts found but scored under 0.9; {len(look_alikes)} scenes without the part "
      "whose best answer scores under 0.9 (look-alikes, not copies)")
print("part | score, reading | same template's best look-alike | share of look-alikes at least as high "
      "by score, by reading")
for i in lost:
    (s, r, _), (sa, ra, _) = present[i], absent.get(i, (float("nan"),) * 3)
    print(f"{i:4} | {s:.2f}, {r:.2f} | {sa:.2f}, {ra:.2f} | "
          f"{(scores >= s).mean():.3f}, {(readings >= r).mean():.3f}")
both = [i for i in present if present[i][2] and i in absent]
print(f"right answers above their template's best look-alike: by score "
      f"{sum(present[i][0] > absent[i][0] for i in both)}, by reading "
      f"{sum(present[i][1] > absent[i][1] for i in both)} of {len(both)}")
