#!/usr/bin/env python3
"""Cut "camera views" of one scene from a large photo, for the fine-tuning experiment in
models/README.md: training views from the left part of the photo, test views from the right
part, so that no part seen in fine-tuning is ever a test template.

    python3 scripts/scene-views.py PHOTO OUT_DIR [--split 0.5] [--train 50] [--test 30]

Each view is a random square crop (0.3 to 0.45 of the photo's height, random
position inside its part), low-passed like a camera's optics, resized to 640x640 and saved as PNG. Needs Pillow (with WebP support
for the gnome-backgrounds photos). Deterministic for a given --seed.
"""

import argparse
import os
import random

from PIL import Image, ImageFilter


def cut_views(photo, box, count, rng, out_dir, prefix):
    left, top, right, bottom = box
    os.makedirs(out_dir, exist_ok=True)
    for i in range(count):
        side = int(rng.uniform(0.3, 0.45) * photo.height)
        side = min(side, right - left, bottom - top)
        x = rng.randint(left, right - side)
        y = rng.randint(top, bottom - side)
        crop = photo.crop((x, y, x + side, y + side))
        # A camera's optics low-pass the scene before its sensor samples it; without this,
        # fine texture (pixels-l's surface stripes) turns into moire that every template matches.
        crop = crop.filter(ImageFilter.GaussianBlur(radius=1.3 * side / 640))
        view = crop.resize((640, 640), Image.LANCZOS)
        view.save(os.path.join(out_dir, f"{prefix}_{i:03d}.png"))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("photo")
    parser.add_argument("out_dir")
    parser.add_argument("--split", type=float, default=0.5,
                        help="fraction of the width used for training views (left part)")
    parser.add_argument("--top", type=float, default=0.0, help="top of the used band (fraction)")
    parser.add_argument("--bottom", type=float, default=1.0, help="bottom of the band (fraction)")
    parser.add_argument("--train", type=int, default=50)
    parser.add_argument("--test", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    photo = Image.open(args.photo).convert("RGB")
    rng = random.Random(args.seed)
    split = int(args.split * photo.width)
    top, bottom = int(args.top * photo.height), int(args.bottom * photo.height)
    cut_views(photo, (0, top, split, bottom), args.train, rng,
              os.path.join(args.out_dir, "train"), "train")
    cut_views(photo, (split, top, photo.width, bottom), args.test, rng,
              os.path.join(args.out_dir, "test"), "test")
    print(f"{args.train} training views and {args.test} test views in {args.out_dir}")


if __name__ == "__main__":
    main()
