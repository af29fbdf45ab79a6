#!/usr/bin/env python3
"""Several templates in one call against one call per template, in steady state.

Writes a batch file that alternates one line naming the first three templates of a saved pair
set (`posematch eval --save DIR`) with three lines naming one each, all in the first pair's
image, runs `posematch match --pairs` on it and compares the lines' `ms` (matching alone; each
template is encoded once, before its first line). Twelve rounds; the first two warm up.

    posematch eval --images /usr/share/backgrounds/mate --count 8 --seed 5 --save /tmp/pairs
    python3 scripts/several-templates-bench.py /tmp/pairs [--posematch target/release/posematch]

Pick a pair set where only the first template is in the first image (the script prints which
templates each way found), as a line with one part among several would be.
"""

import argparse
import json
import statistics
import subprocess
from pathlib import Path

ROUNDS, WARM_UP = 12, 2

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("pairs", type=Path, help="folder written by `posematch eval --save`")
parser.add_argument("--posematch", default="target/release/posematch")
parser.add_argument("extra", nargs="*", help="further `posematch match` options")
args = parser.parse_args()

pairs = [json.loads(line) for line in (args.pairs / "pairs.jsonl").open()]
templates = [p["template"] for p in pairs[:3]]
image = pairs[0]["image"]
batch, out = args.pairs / "several-templates.jsonl", args.pairs / "several-templates-out.jsonl"
with batch.open("w") as f:
    for r in range(ROUNDS):
        f.write(json.dumps({"id": f"one-{r}", "templates": templates, "image": image}) + "\n")
        for k, t in enumerate(templates):
            f.write(json.dumps({"id": f"single{k}-{r}", "template": t, "image": image}) + "\n")
subprocess.run([args.posematch, "match", "--pairs", str(batch), "--out", str(out), *args.extra],
               check=True)
answers = {a["id"]: a for a in map(json.loads, out.open())}
one = [answers[f"one-{r}"]["ms"] for r in range(WARM_UP, ROUNDS)]
three = [sum(answers[f"single{k}-{r}"]["ms"] for k in range(3)) for r in range(WARM_UP, ROUNDS)]
m1, m3 = statistics.median(one), statistics.median(three)
print(f"one call: median {m1:.1f} ms (min {min(one):.1f}, max {max(one):.1f})")
print(f"three calls: median {m3:.1f} ms (min {min(three):.1f}, max {max(three):.1f})")
print(f"ratio of the medians: {m1 / m3:.2f}")
last = ROUNDS - 1
print("found in one call:",
      [(p.get("template"), round(p["score"], 3)) for p in answers[f"one-{last}"]["poses"]])
print("found in three calls:",
      [[round(p["score"], 3) for p in answers[f"single{k}-{last}"]["poses"]] for k in range(3)])
