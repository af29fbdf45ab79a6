"""Weights between two runs of the same network: `(1 - alpha) * base + alpha * tuned`, tensor by
tensor (BatchNorm statistics included; integer counters are taken from `tuned`).

Why: a fine-tune on a new mix (wider scales, long parts) gains there and loses some of what the
base did well. A fine-tune of the same weights stays in one basin of the loss, so every weight
on the line between the two is a working network, and alpha trades one for the other (the
weight-space ensembles of Wortsman et al., "Robust fine-tuning of zero-shot models", 2022).
Choose alpha on a tuning set, never on held-out data (models/README.md records the 2026-11-26
choice).

    python3 training/interpolate.py --base data/init.safetensors --tuned weights-step1404.pth \
        --alpha 0.5 --out mix.pth
    posematch weights import --from mix.pth --out mix.bpk
"""

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import train as T  # noqa: E402


def interpolate(base, tuned, alpha):
    """`(1 - alpha) * base + alpha * tuned` for every floating-point tensor of `tuned`; the two
    must hold the same floating-point tensors with the same shapes."""
    if not 0.0 <= alpha <= 1.0:
        raise SystemExit(f"--alpha {alpha}: use a value in [0, 1]")
    floats = {k for k, v in tuned.items() if v.is_floating_point()}
    problems = [f"{k}: missing in the base" for k in sorted(floats) if k not in base]
    problems += [f"{k}: shape {tuple(base[k].shape)} in the base, {tuple(tuned[k].shape)} tuned"
                 for k in sorted(floats) if k in base and base[k].shape != tuned[k].shape]
    if problems:
        raise SystemExit("the weights do not belong to one network: " + "; ".join(problems[:5]))
    return {k: ((1.0 - alpha) * base[k].to(v.dtype) + alpha * v) if k in floats else v.clone()
            for k, v in tuned.items()}


def main(argv=None):
    a = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    a.add_argument("--base", required=True, help="the weights at alpha 0 (.safetensors or .pth)")
    a.add_argument("--tuned", required=True, help="the weights at alpha 1 (.safetensors or .pth)")
    a.add_argument("--alpha", type=float, required=True, help="share of --tuned, 0..1")
    a.add_argument("--out", required=True, help=".pth to write (posematch weights import reads it)")
    args = a.parse_args(argv)
    mixed = interpolate(T.read_weights(args.base), T.read_weights(args.tuned), args.alpha)
    T.atomic_save(mixed, args.out)
    print(f"wrote {args.out}: {1 - args.alpha:g} x {args.base} + {args.alpha:g} x {args.tuned}")


if __name__ == "__main__":
    main()
