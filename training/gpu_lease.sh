#!/usr/bin/env bash
# A whole GPU lease in one device call: the three steps that made the shipped default
# (models/README.md, 2026-11-26) — a wide-scale fine-tune of the shipped weights, the halfway
# interpolation with them, and a short S1.5 cool-down from that — so that no second machine
# start (1-2 device minutes) is paid. What comes back (at most 8 files):
#
#   OUT/a/log.txt, OUT/a/weights-step<N>.pth   the wide-scale run (every 2 minutes and its end)
#   OUT/b/log.txt, OUT/b/weights-step<N>.pth   the cool-down from the mix (its end: the candidate)
#   OUT/a/trained_on.json, OUT/b/trained_on.json  each run's training record: import the candidate
#     with --trained-on default --trained-on OUT/a/trained_on.json --trained-on OUT/b/trained_on.json
#
#   training/gpu_lease.sh OUT WIDE_MINUTES COOL_MINUTES
#
# The mix is the shipped recipe's unless the environment says otherwise: WIDE_LEVEL (S1.5,S2.5),
# COOL_LEVEL (S1.5), ASPECT (3.5), ELONGATED (0.5), CROWD (share of crowded pairs, 0.3),
# COOL_CROWD (the cool-down's, CROWD; 0 keeps the cool-down single-instance), ALPHA (0.5),
# WIDE_LR (3e-4), COOL_LR (1e-4), RATE (planned pairs/s, compiled, 2900).
# Each schedule is planned to end at its floor 0.9 minutes before its run's time is up (the
# compile warm-up counts against the minutes). Choose between the candidate, the wide run, other
# alphas (interpolate.py on the CPU) and the shipped default on the tuning set, never on held-out
# data.
set -u
out=${1:?OUT folder}
wide=${2:?minutes of the wide-scale run}
cool=${3:?minutes of the cool-down}
here=$(cd "$(dirname "$0")" && pwd)
cd "$here"
export MEASURE=0 MODES=${MODES:-compile} RATE=${RATE:-2900} ASPECT=${ASPECT:-3.5} ELONGATED=${ELONGATED:-0.5}
export CROWD=${CROWD:-0.3}
schedule() { awk -v m="$1" 'BEGIN { s = m - 0.9; if (s < m / 2) s = m / 2; printf "%.2f", s }'; }

LEVEL=${WIDE_LEVEL:-S1.5,S2.5} LR=${WIDE_LR:-3e-4} WARMUP=150 \
  ./gpu_finetune.sh "$out/a" "$wide" "$(schedule "$wide")" || exit 1
tuned=$(ls -v "$out"/a/weights-step*.pth 2>/dev/null | tail -n 1)
[ -n "$tuned" ] || { echo "the wide-scale run saved no weights" >&2; exit 1; }
mix=/tmp/posematch-mix.pth
python3 interpolate.py --base data/init.safetensors --tuned "$tuned" --alpha "${ALPHA:-0.5}" \
  --out "$mix" 2>&1 | tee -a "$out/a/log.txt" || exit 1
INIT=$mix LEVEL=${COOL_LEVEL:-S1.5} LR=${COOL_LR:-1e-4} WARMUP=50 CROWD=${COOL_CROWD:-$CROWD} \
  ./gpu_finetune.sh "$out/b" "$cool" "$(schedule "$cool")"
