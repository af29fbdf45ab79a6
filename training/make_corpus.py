"""Builds the training corpus on the CPU machine: photos from Debian wallpaper packages, each
decoded once (WebP too), downscaled to at most 640 px and stored as JPEG in one folder small
enough (<= 40 MiB) to travel with the working tree to the GPU machine.

    python3 training/make_corpus.py --install --out training/data/corpus

Held out, never in the corpus: mate-backgrounds (our evaluation set), lomiri-wallpapers (the
tuning set of the verification knobs), and the independent evaluation data that no project
code may train, tune or select on: scikit-image's sample images and Debian's jigzo-data,
hugin-data and xplanet-images.
"""

import argparse
import hashlib
import io
import re
import subprocess
import sys
from pathlib import Path

from PIL import Image

DEFAULT_PACKAGES = [
    "plasma-workspace-wallpapers",
    "ukui-wallpapers",
    "sway-backgrounds",
    "gnome-backgrounds",
    "supertuxkart-data",
]
# Per package: which files (regular expression on the path), which not, and at most how many
# (a fixed pseudo-random choice). The game's textures (metal, stone, wood, signs, panels) add the
# man-made surfaces that wallpapers lack; their normal, specular and mask maps are no photos.
RULES = {
    "supertuxkart-data": (r"/data/(textures|tracks)/",
                          r"(normal|_n\.|_nm\.|nrm|mask|spec|gloss|_ao|height|bump|light|shadow|"
                          r"_sh\.|alpha|sky|cloud|font|icon|gui)", 400),
}
HELD_OUT = {
    "mate-backgrounds": "our evaluation set",
    "lomiri-wallpapers": "the tuning set of the verification knobs",
    "lomiri-wallpapers-16.04": "the tuning set of the verification knobs",
    "lomiri-wallpapers-20.04": "the tuning set of the verification knobs",
    "jigzo-data": "reserved for independent evaluation",
    "hugin-data": "reserved for independent evaluation",
    "xplanet-images": "reserved for independent evaluation",
}
HELD_OUT_PATHS = ("/usr/share/backgrounds/mate", "skimage", "scikit_image", "/jigzo", "/hugin",
                  "/xplanet", "lomiri")
SUFFIXES = (".png", ".jpg", ".jpeg", ".webp")
MAX_SIDE = 640
BUDGET_BYTES = 40 * 1024 * 1024


def package_files(package):
    out = subprocess.run(["dpkg", "-L", package], capture_output=True, text=True)
    if out.returncode != 0:
        return None
    return [Path(line) for line in out.stdout.splitlines()
            if line.lower().endswith(SUFFIXES) and Path(line).is_file()]


def install(packages):
    missing = [p for p in packages if package_files(p) is None]
    if missing:
        subprocess.run(["apt-get", "update", "-qq"], check=True)
        subprocess.run(["apt-get", "install", "-y", "-qq", "--no-install-recommends", *missing],
                       check=True, env={"DEBIAN_FRONTEND": "noninteractive", "PATH": "/usr/bin:/bin:/usr/sbin:/sbin"})


def main(argv=None):
    a = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    a.add_argument("--out", default="training/data/corpus")
    a.add_argument("--packages", nargs="*", default=DEFAULT_PACKAGES)
    a.add_argument("--install", action="store_true", help="apt-get install missing packages (root)")
    a.add_argument("--quality", type=int, default=90)
    args = a.parse_args(argv)
    for package in args.packages:
        if package in HELD_OUT:
            a.error(f"{package} is held out ({HELD_OUT[package]}): it never goes into training")
    if args.install:
        install(args.packages)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    seen, total, written = set(), 0, 0
    for package in args.packages:
        files = package_files(package)
        if files is None:
            sys.exit(f"{package} is not installed: run with --install (as root) or apt-get install it")
        n = 0
        include, exclude, cap = RULES.get(package, (None, None, None))
        if include:
            files = [f for f in files if re.search(include, str(f)) and not re.search(exclude, str(f).lower())]
            files.sort(key=lambda f: hashlib.sha1(str(f).encode()).hexdigest())
        for path in files if include else sorted(files):
            if cap is not None and n >= cap:
                break
            if path.is_symlink() or any(marker in str(path) for marker in HELD_OUT_PATHS):
                continue
            try:
                with Image.open(path) as im:
                    if "A" in im.getbands() and min(im.getchannel("A").getextrema()) < 250:
                        continue  # transparent parts: no photo there
                    im = im.convert("RGB")
                    if min(im.size) < 256:
                        continue  # icons and thumbnails
                    scale = MAX_SIDE / max(im.size)
                    if scale < 1:
                        im = im.resize((round(im.width * scale), round(im.height * scale)),
                                       Image.LANCZOS)
                    buffer = io.BytesIO()
                    im.save(buffer, "JPEG", quality=args.quality)
            except Exception as error:
                print(f"skipping {path}: {error}", file=sys.stderr)
                continue
            data = buffer.getvalue()
            digest = hashlib.sha1(data).hexdigest()[:12]
            if digest in seen:
                continue  # the same picture in another size or package
            seen.add(digest)
            (out / f"{package}--{path.stem}--{digest}.jpg").write_bytes(data)
            total += len(data)
            written += 1
            n += 1
        print(f"{package}: {n} photos")
    print(f"{written} photos, {total / 2**20:.1f} MiB in {out}")
    if total > BUDGET_BYTES:
        sys.exit(f"the corpus is {total / 2**20:.1f} MiB, over the 40 MiB that travel: lower --quality")


if __name__ == "__main__":
    main()
