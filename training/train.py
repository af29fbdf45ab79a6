"""Trains the TDCM network from random initialisation on pairs cut on the device.

A run is bounded (`--minutes`) and resumable: it ends cleanly, writing `checkpoint.pt`
(weights, optimizer, step, generator states; a few MiB) and `weights.pth` (the state dict alone,
which `posematch weights import` reads) atomically into `--out`; `--resume` continues from
there with the same schedule. See training/README.md for the whole sequence.

    python3 training/train.py --corpus data/corpus --out data/run --steps 20000 --minutes 8
"""

import argparse
import json
import math
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import pairs as P  # noqa: E402
from tdcm import Tdcm, normalise  # noqa: E402

MAX_PHOTO_SIDE = 640
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".webp", ".bmp", ".tif", ".tiff"}


def load_photos(folder, max_side=MAX_PHOTO_SIDE):
    """Every decodable image under `folder`, sorted by path, RGB uint8, at most `max_side`."""
    from PIL import Image

    files = sorted(p for p in Path(folder).rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES)
    photos, names = [], []
    for path in files:
        try:
            with Image.open(path) as im:
                im = im.convert("RGB")
                scale = max_side / max(im.size)
                if scale < 1:
                    size = (max(1, round(im.width * scale)), max(1, round(im.height * scale)))
                    im = im.resize(size, Image.BILINEAR, reducing_gap=None)
                photos.append(np.asarray(im, dtype=np.uint8).copy())
                names.append(str(path))
        except Exception as error:  # a broken file is skipped, not fatal
            print(f"skipping {path}: {error}", file=sys.stderr)
    return photos, names


def split(photos, names, every=10):
    """Every `every`-th photo (by path) is held out for the progress check (the last one when
    there are fewer)."""
    held_out = {i for i in range(len(photos)) if i % every == every - 1} or {len(photos) - 1}
    if len(photos) < 2:
        return photos, []
    train = [p for i, p in enumerate(photos) if i not in held_out]
    held = [p for i, p in enumerate(photos) if i in held_out]
    return train, held


def atomic_save(obj, path):
    tmp = Path(str(path) + ".tmp")
    torch.save(obj, tmp)
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    os.replace(tmp, path)


def atomic_write_text(path, text):
    tmp = Path(str(path) + ".tmp")
    with open(tmp, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def export_weights(model, path):
    """The state dict alone, float32 on the CPU, with the official key names."""
    state = {k: v.detach().to("cpu", copy=True) for k, v in model.state_dict().items()}
    state = {k: (v.float() if v.is_floating_point() else v) for k, v in state.items()}
    atomic_save(state, path)


def parse_args(argv=None):
    a = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    a.add_argument("--corpus", required=True, help="folder of training photos")
    a.add_argument("--validation", help="folder of held-out photos (default: every 10th corpus photo)")
    a.add_argument("--out", required=True, help="run folder: checkpoint.pt, weights.pth, log.txt")
    a.add_argument("--resume", action="store_true", help="continue from --out/checkpoint.pt")
    a.add_argument("--init-weights",
                   help="start from these weights instead of random initialisation: a "
                        ".safetensors file from `posematch weights export` or a .pth of "
                        "train.py or interpolate.py (our own weights only, never the authors'); "
                        "a fresh optimizer and schedule")
    a.add_argument("--steps", type=int, default=20000, help="steps of the whole schedule (all runs)")
    a.add_argument("--minutes", type=float, default=8.0, help="stop this run after this many minutes")
    a.add_argument("--fit-schedule", type=float, metavar="MINUTES",
                   help="re-plan --steps once, inside the warm-up, from the rate measured since "
                        "the compile so that the schedule ends at its floor MINUTES after the "
                        "run's start: a time-bounded run whose pairs/s is not known beforehand")
    a.add_argument("--batch", type=int, default=64)
    a.add_argument("--search-size", type=int, default=224)
    a.add_argument("--level", default="S1.5", help="level or comma list (S1, S1.5, S2, S2.5)")
    a.add_argument("--elongated-share", type=float, default=0.0,
                   help="share of pairs showing elongated parts (aspect log-uniform up to --aspect-max; pairs.cut_pairs)")
    a.add_argument("--aspect-max", type=float, default=2.5,
                   help="largest sx/sy (and sy/sx) of the elongated pairs")
    a.add_argument("--crowd-share", type=float, default=0.0,
                   help="share of pairs showing 1 to --crowd-max more copies of the part (pairs.add_crowd)")
    a.add_argument("--crowd-max", type=int, default=5, help="most extra copies in a crowded pair")
    a.add_argument("--lr", type=float, default=1e-3)
    a.add_argument("--weight-decay", type=float, default=0.05)
    a.add_argument("--warmup", type=int, default=500)
    a.add_argument("--seed", type=int, default=0)
    a.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    a.add_argument("--no-bf16", action="store_true", help="float32 throughout (default bf16 autocast on CUDA)")
    a.add_argument("--compile", action="store_true", help="torch.compile the model")
    a.add_argument("--save-every", type=float, default=2.0,
                   help="minutes between checkpoints (a run killed mid-way loses at most this much)")
    a.add_argument("--snapshots",
                   help="also keep each saved weights.pth as SNAPSHOTS/weights-step<N>.pth (a "
                        "learning curve to evaluate, and a choice on a tuning set afterwards)")
    a.add_argument("--log-every", type=int, default=100)
    a.add_argument("--validate-every", type=int, default=1000)
    a.add_argument("--validation-pairs", type=int, default=256)
    a.add_argument("--overfit-one-batch", action="store_true",
                   help="train on one fixed batch (a check that the network and losses can fit)")
    a.add_argument("--threads", type=int, default=0, help="CPU threads (0: torch's default)")
    args = a.parse_args(argv)
    if args.batch < 1 or args.steps < 1 or args.minutes <= 0:
        a.error("--batch, --steps and --minutes must be positive")
    if args.fit_schedule is not None and (args.resume or not 0 < args.fit_schedule <= args.minutes):
        a.error("--fit-schedule needs a new run and 0 < MINUTES <= --minutes")
    if not 0.0 <= args.crowd_share <= 1.0 or not 1 <= args.crowd_max <= 16:
        a.error("--crowd-share must lie in [0, 1] and --crowd-max in 1..16")
    if args.search_size % 4 or not 64 <= args.search_size <= 1024:
        a.error("--search-size must be a multiple of 4 in 64..1024")
    for name in args.level.split(","):
        if name not in P.LEVELS:
            a.error(f"unknown level {name}: use S1, S1.5, S2 or S2.5")
    if args.init_weights and args.resume:
        a.error("--init-weights starts a new run; --resume continues one: choose one")
    return args


def trained_on(args, pairs_seen):
    """What this run's pairs were drawn from, as `posematch weights import --trained-on` reads it
    (src/model/network/trained_on.rs): `throughout` the shapes every pair could take (the
    scale range all of the run's levels share), `seen` everything any pair could (the widest
    level, its independent axis scales, elongated parts). On the template grid; axis scales
    are object side over grid side."""
    ranges = [P.LEVELS[name] for name in args.level.split(",")]
    shared = (max(lo for lo, _ in ranges), min(hi for _, hi in ranges))
    widest = (min(lo for lo, _ in ranges), max(hi for _, hi in ranges))
    seen_aspect = widest[1] / widest[0]
    if args.elongated_share > 0:
        # Elongated pairs are kept only within what the heads express (P.HEAD_SCALES).
        head_lo, head_hi = P.HEAD_SCALES
        seen_aspect = max(seen_aspect, min(args.aspect_max, head_hi / head_lo))
    crowd = f", {100 * args.crowd_share:.0f} % crowded (up to {1 + args.crowd_max} parts)" \
        if args.crowd_share > 0 else ""
    elongated = f", {100 * args.elongated_share:.0f} % elongated (aspect to {args.aspect_max})" \
        if args.elongated_share > 0 else ""
    start = f"from {args.init_weights}" if args.init_weights else "from random initialisation"
    return {
        "throughout": {"grid_scales": list(shared), "aspect_max": shared[1] / shared[0]},
        "seen": {"grid_scales": list(widest), "aspect_max": seen_aspect},
        "template_sides": [[36, 36]],
        "parts_per_window_max": 1 + args.crowd_max if args.crowd_share > 0 else 1,
        "search_sides": [args.search_size],
        "pairs": pairs_seen,
        "runs": [f"{time.strftime('%Y-%m-%d')} training/train.py: {pairs_seen} pairs, {args.level}, "
                 f"search {args.search_size} px{elongated}{crowd}, {start}"],
    }


SAFETENSORS_DTYPES = {"F32": np.float32, "F16": np.float16, "I64": np.int64}


def read_safetensors(path):
    """A safetensors file as {name: CPU tensor}, read without the `safetensors` package (the GPU
    machine may lack it): an 8-byte little-endian header length, a JSON header, raw data."""
    raw = Path(path).read_bytes()
    length = int.from_bytes(raw[:8], "little")
    header = json.loads(raw[8:8 + length])
    data = raw[8 + length:]
    tensors = {}
    for name, info in header.items():
        if name == "__metadata__":
            continue
        if info["dtype"] not in SAFETENSORS_DTYPES:
            raise SystemExit(f"{path}: tensor {name} has dtype {info['dtype']}, not one we read")
        start, end = info["data_offsets"]
        array = np.frombuffer(data[start:end], dtype=SAFETENSORS_DTYPES[info["dtype"]])
        tensors[name] = torch.from_numpy(array.reshape(info["shape"]).copy())
    return tensors


def read_weights(path):
    """A state dict from a `.safetensors` (`posematch weights export`) or a `.pth` (train.py's
    export, interpolate.py's mix)."""
    if str(path).endswith(".safetensors"):
        return read_safetensors(path)
    state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict):
        raise SystemExit(f"{path}: not a state dict")
    return state


def load_init_weights(model, path):
    """Loads `path` (see `read_weights`) into `model`; every parameter and buffer must be there
    with its shape except BatchNorm's `num_batches_tracked` counters (training bookkeeping,
    which our export omits)."""
    tensors = read_weights(path)
    expected = model.state_dict()
    problems = [f"{k}: missing" for k in expected
                if k not in tensors and not k.endswith("num_batches_tracked")]
    problems += [f"{k}: not in the model" for k in tensors if k not in expected]
    problems += [f"{k}: shape {tuple(v.shape)}, model {tuple(expected[k].shape)}"
                 for k, v in tensors.items() if k in expected and v.shape != expected[k].shape]
    if problems:
        raise SystemExit(f"--init-weights {path} does not fit the model: " + "; ".join(problems[:5]))
    model.load_state_dict(tensors, strict=False)


def train(args):
    started = time.monotonic()
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log = open(out / "log.txt", "a", buffering=1)

    def say(line):
        print(line, flush=True)
        log.write(line + "\n")

    photos, names = load_photos(args.corpus)
    if args.validation:
        train_photos = photos
        held_photos, _ = load_photos(args.validation)
    else:
        train_photos, held_photos = split(photos, names)
    if not train_photos or not held_photos:
        raise SystemExit(f"{args.corpus}: need photos for training and for the progress check")
    bank = P.PhotoBank(train_photos, device)
    held_bank = P.PhotoBank(held_photos, device)
    levels = args.level.split(",")

    torch.manual_seed(args.seed)
    model = Tdcm().to(device)
    use_bf16 = device.type == "cuda" and not args.no_bf16
    if device.type == "cuda":
        model = model.to(memory_format=torch.channels_last)
        torch.backends.cudnn.benchmark = True
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
    fused = device.type == "cuda"
    optimizer = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=args.weight_decay,
                                  fused=fused)
    gen = torch.Generator(device=device)
    gen.manual_seed(args.seed * 1_000_003 + 1)
    step = 0
    pairs_seen = 0
    checkpoint = out / "checkpoint.pt"
    if args.resume:
        if not checkpoint.is_file():
            raise SystemExit(f"--resume: {checkpoint} does not exist")
        state = torch.load(checkpoint, map_location=device, weights_only=False)
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        step, pairs_seen = state["step"], state["pairs_seen"]
        gen.set_state(state["generator"].to("cpu") if device.type == "cpu" else state["generator"].cpu())
        torch.set_rng_state(state["torch_rng"].cpu())
        if device.type == "cuda" and state.get("cuda_rng") is not None:
            torch.cuda.set_rng_state(state["cuda_rng"].cpu())
        say(f"resumed at step {step} ({pairs_seen} pairs seen)")
    elif args.init_weights:
        load_init_weights(model, args.init_weights)
        say(f"from {args.init_weights} (seed {args.seed}); {len(train_photos)} training photos, "
            f"{len(held_photos)} held out")
    else:
        say(f"from random initialisation (seed {args.seed}); {len(train_photos)} training photos, "
            f"{len(held_photos)} held out")
    forward = torch.compile(model) if args.compile else model

    # A fixed progress-check set from the held-out photos.
    held_gen = torch.Generator(device=device)
    held_gen.manual_seed(12345)
    with torch.no_grad():
        held = P.cut_pairs(held_bank, args.validation_pairs, levels, search_side=args.search_size,
                          gen=held_gen, elongated_share=args.elongated_share,
                          aspect_max=args.aspect_max)

    def check():
        model.eval()
        hits = []
        with torch.no_grad(), torch.autocast(device.type, dtype=torch.bfloat16, enabled=use_bf16):
            for i in range(0, held.templates.shape[0], 64):
                maps = model(normalise(held.templates[i:i + 64]), normalise(held.searches[i:i + 64]))
                hits.append(P.peak_hits(maps.float(), held.truth[i:i + 64]) * maps.shape[0])
        model.train()
        return sum(hits) / held.templates.shape[0]

    def save():
        atomic_save({
            "model": model.state_dict(), "optimizer": optimizer.state_dict(), "step": step,
            "pairs_seen": pairs_seen, "generator": gen.get_state(),
            "torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state() if device.type == "cuda" else None,
            "args": vars(args),
        }, checkpoint)
        export_weights(model, out / "weights.pth")
        atomic_write_text(out / "trained_on.json", json.dumps(trained_on(args, pairs_seen), indent=1))
        if args.snapshots:
            Path(args.snapshots).mkdir(parents=True, exist_ok=True)
            shutil.copyfile(out / "weights.pth", Path(args.snapshots) / f"weights-step{step}.pth")

    model.train()
    window_start, window_pairs = time.monotonic(), 0
    window_loss, window_steps = 0.0, 0
    deadline = started + args.minutes * 60
    next_save = time.monotonic() + args.save_every * 60
    fixed = None
    # --fit-schedule: time steps FIT_FROM..fit_at (the compile lies before FIT_FROM), then re-plan
    # the total before the warm-up ends, so that no step already taken saw another schedule.
    fit_from, fit_started = 10, None
    fit_at = max(fit_from + 10, min(args.warmup, 60))
    while step < args.steps and time.monotonic() < deadline:
        if args.fit_schedule is not None and step == fit_from:
            fit_started = time.monotonic()
        if fit_started is not None and step == fit_at:
            seconds_per_step = (time.monotonic() - fit_started) / (fit_at - fit_from)
            left = started + args.fit_schedule * 60 - time.monotonic()
            args.steps = step + max(1, int(left / seconds_per_step))
            fit_started = None
            say(f"fit: {args.batch / seconds_per_step:.0f} pairs/s over steps {fit_from}-{fit_at} "
                f"-> --steps {args.steps} to end at {args.fit_schedule:.2f} min")
        lr = P.learning_rate(step, args.steps, args.lr, args.warmup)
        for group in optimizer.param_groups:
            group["lr"] = lr
        if fixed is None:
            with torch.no_grad():
                batch = P.cut_pairs(bank, args.batch, levels, search_side=args.search_size, gen=gen,
                                    elongated_share=args.elongated_share,
                                    aspect_max=args.aspect_max)
                searches, instances, present = P.add_crowd(bank, batch, args.crowd_share, gen,
                                                           max_extra=args.crowd_max)
                searches = P.jitter(searches, gen)
                labels = P.render_labels(instances, args.search_size, args.search_size,
                                         present=present)
                templates = normalise(batch.templates)
                searches = normalise(searches)
                if device.type == "cuda":
                    templates = templates.contiguous(memory_format=torch.channels_last)
                    searches = searches.contiguous(memory_format=torch.channels_last)
            if args.overfit_one_batch:
                fixed = (templates, searches, labels)
        else:
            templates, searches, labels = fixed
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=use_bf16):
            maps = forward(templates, searches)
        loss, terms = P.losses(maps, labels)
        if not torch.isfinite(loss):
            raise SystemExit(f"step {step}: the loss is not finite ({loss.item()}); lower --lr")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
        optimizer.step()
        step += 1
        pairs_seen += args.batch
        window_pairs += args.batch
        window_loss = window_loss + loss.detach()
        window_steps += 1
        if step % args.log_every == 0 or step == args.steps:
            now = time.monotonic()
            rate = window_pairs / (now - window_start)
            window_start, window_pairs = now, 0
            parts = " ".join(f"{k} {v.item():.3f}" for k, v in terms.items())
            mean_loss = (window_loss / window_steps).item()
            window_loss, window_steps = 0.0, 0
            # loss: mean over the steps since the last line; the terms: this step's.
            say(f"step {step}/{args.steps} loss {mean_loss:.4f} ({parts}) lr {lr:.2e} "
                f"{rate:.0f} pairs/s, {pairs_seen} pairs, {(now - started) / 60:.1f} min")
        if time.monotonic() >= next_save:
            save()
            next_save = time.monotonic() + args.save_every * 60
        if step % args.validate_every == 0:
            say(f"step {step}: held-out peak within 3 px: {100 * check():.1f} % "
                f"({held.templates.shape[0]} pairs)")
    save()
    say(f"stopped at step {step} ({pairs_seen} pairs seen) after {(time.monotonic() - started) / 60:.1f} min; "
        f"held-out peak within 3 px: {100 * check():.1f} %; wrote {checkpoint} and {out / 'weights.pth'}")
    return step


if __name__ == "__main__":
    train(parse_args())
