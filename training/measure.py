"""Pairs per second of the training step (pair cutting + forward + backward + AdamW) for a few
batch sizes and search-crop sizes, to choose them by measurement in the first minute on a GPU.

    python3 training/measure.py --corpus training/data/corpus --batches 64,128,256 --sizes 160,224
"""

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import pairs as P  # noqa: E402
from tdcm import Tdcm, normalise  # noqa: E402
from train import load_photos  # noqa: E402


def step_rate(bank, batch, size, device, bf16, compile_model, steps=12, warmup=4):
    """Pairs per second over `steps` timed steps, and the share of that time spent cutting
    pairs. The device is synchronised before and after the cutting, so the share is the
    cutting's own (a share timed without the first sync also counts the previous step's
    backward pass, still running when the cutting starts, which made the last GPU run's
    62-89 % an overstatement)."""
    model = Tdcm().to(device)
    if device.type == "cuda":
        model = model.to(memory_format=torch.channels_last)
    forward = torch.compile(model) if compile_model else model
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-4, fused=device.type == "cuda")
    gen = torch.Generator(device=device).manual_seed(0)
    timings = {}

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize()

    for i in range(warmup + steps):
        if i == warmup:
            sync()
            start = time.perf_counter()
            data_time = 0.0
        if i >= warmup:
            sync()
        t0 = time.perf_counter()
        with torch.no_grad():
            b = P.cut_pairs(bank, batch, "S1.5", search_side=size, gen=gen)
            searches = normalise(P.jitter(b.searches, gen))
            labels = P.render_labels(b.truth, size, size)
            templates = normalise(b.templates)
        if i >= warmup:
            sync()
            data_time += time.perf_counter() - t0
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
            maps = forward(templates, searches)
        loss, _ = P.losses(maps, labels)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    sync()
    elapsed = time.perf_counter() - start
    timings["pairs_per_s"] = steps * batch / elapsed
    timings["data_share"] = data_time / elapsed
    if device.type == "cuda":
        timings["peak_gib"] = torch.cuda.max_memory_allocated() / 2**30
        torch.cuda.reset_peak_memory_stats()
    return timings


def profile(bank, batch, size, device, bf16, path):
    """Operators of three eager training steps by self device time (CPU time on the CPU), so a
    GPU lease says where a step goes, the cutting included."""
    from torch.profiler import ProfilerActivity, profile as torch_profile
    activities = [ProfilerActivity.CPU]
    if device.type == "cuda":
        activities.append(ProfilerActivity.CUDA)
    step_rate(bank, batch, size, device, bf16, False, steps=1, warmup=2)
    with torch_profile(activities=activities) as prof:
        step_rate(bank, batch, size, device, bf16, False, steps=3, warmup=0)
    key = "self_cuda_time_total" if device.type == "cuda" else "self_cpu_time_total"
    table = prof.key_averages().table(sort_by=key, row_limit=40)
    path.write_text(table)
    print("\n".join(table.splitlines()[:20]))


def main():
    a = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    a.add_argument("--corpus", required=True)
    a.add_argument("--batches", default="64,128,256")
    a.add_argument("--sizes", default="160,224")
    a.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    a.add_argument("--no-bf16", action="store_true")
    a.add_argument("--modes", default="eager",
                   help="comma list of eager, compile (torch.compile the model; its compile time "
                        "falls in the warm-up steps, outside the timing)")
    a.add_argument("--profile", help="profile three eager steps of the first batch and size, "
                                       "writing the operators by device time to this file")
    a.add_argument("--choose", help="write the fastest 'batch size pairs/s mode' to this file")
    args = a.parse_args()
    device = torch.device(args.device)
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
        print(torch.cuda.get_device_name(), torch.__version__)
    photos, _ = load_photos(args.corpus)
    bank = P.PhotoBank(photos, device)
    bf16 = device.type == "cuda" and not args.no_bf16
    if args.profile:
        first_batch = int(args.batches.split(",")[0])
        first_size = int(args.sizes.split(",")[0])
        profile(bank, first_batch, first_size, device, bf16, Path(args.profile))
    modes = args.modes.split(",")
    for mode in modes:
        if mode not in ("eager", "compile"):
            a.error(f"unknown mode {mode}: use eager or compile")
    print(f"{len(photos)} photos; bf16 {bf16}")
    print("mode     batch  size  pairs/s  cutting share  peak GiB")
    rates = []
    for mode in modes:
        for size in (int(s) for s in args.sizes.split(",")):
            for batch in (int(b) for b in args.batches.split(",")):
                try:
                    t = step_rate(bank, batch, size, device, bf16, mode == "compile")
                except Exception as error:  # a mode that fails here is simply not chosen
                    print(f"{mode:7}  {batch:5}  {size:4}  failed: {str(error)[:300]}", flush=True)
                    continue
                print(f"{mode:7}  {batch:5}  {size:4}  {t['pairs_per_s']:7.0f}"
                      f"  {100 * t['data_share']:12.0f} %  {t.get('peak_gib', 0):8.1f}", flush=True)
                rates.append((t["pairs_per_s"], batch, size, mode))
    if args.choose and rates:
        rate, batch, size, mode = max(rates)
        Path(args.choose).write_text(f"{batch} {size} {rate:.0f} {mode}\n")
        print(f"fastest: {mode}, batch {batch}, search size {size}, {rate:.0f} pairs/s -> {args.choose}")


if __name__ == "__main__":
    main()
