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
#   OUT/measure.txt   measure.py's eager pairs/s at MEASURE_BATCHES (default 512,1024; crop 160)
#     before training, against the last run's (MEASURE_BATCHES=none skips it)
#   OUT/snapshots.tar  every earlier save of a and b (the learning curve), so that what comes back
#     stays within the device tool's 8 files
#
#   training/gpu_lease.sh OUT WIDE_MINUTES COOL_MINUTES
#
# The mix is the shipped recipe's unless the environment says otherwise: WIDE_LEVEL (S1.5,S2.5),
# COOL_LEVEL (S1.5), ASPECT (3.5), ELONGATED (0.5), CROWD (share of crowded pairs, 0.3),
# COOL_CROWD (the cool-down's, CROWD; 0 keeps the cool-down single-instance), ALPHA (0.5),
# WIDE_LR (3e-4), COOL_LR (1e-4), RATE (planned pairs/s, compiled, 2900), FIT (1: each run
# re-plans its steps from its own rate, gpu_finetune.sh).
# Each schedule is planned to end at its floor 0.4 minutes (FIT=1; else 0.9) before its run's
# time is up (the compile warm-up counts against the minutes). Choose between the candidate, the wide run, other
# alphas (interpolate.py on the CPU) and the shipped default on the tuning set, never on held-out
# data.
set -u
out=${1:?OUT folder}
wide=${2:?minutes of the wide-scale run}
cool=${3:?minutes of the cool-down}
here=$(cd "$(dirname "$0")" && pwd)
cd "$here"
export MEASURE=0 MODES=${MODES:-compile} RATE=${RATE:-2900} ASPECT=${ASPECT:-3.5} ELONGATED=${ELONGATED:-0.5}
export CROWD=${CROWD:-0.3} FIT=${FIT:-1}
mkdir -p "$out"
batches=${MEASURE_BATCHES:-512,1024}
if [ "$batches" != none ]; then
  PYTHONUNBUFFERED=1 timeout 90 python3 measure.py --corpus data/corpus --batches "$batches" \
    --sizes 160 --modes eager 2>&1 | tee "$out/measure.txt"
fi
# The earlier saves of each run go into one tar, the last stays beside its log.
pack_snapshots() {
  local earlier=()
  for run in a b; do
    mapfile -t saves < <(ls -v "$out/$run"/weights-step*.pth 2>/dev/null)
    [ "${#saves[@]}" -gt 1 ] && earlier+=("${saves[@]:0:${#saves[@]}-1}")
  done
  [ "${#earlier[@]}" -gt 0 ] || return 0
  tar -cf "$out/snapshots.tar" -C "$out" "${earlier[@]#"$out"/}" && rm -f "${earlier[@]}"
}
trap pack_snapshots EXIT
# A fitted schedule (FIT=1) keeps 0.4 minutes for the last save and check; a planned one 0.9 for
# a RATE that may be off.
margin=$([ "$FIT" = 1 ] && echo 0.4 || echo 0.9)
schedule() { awk -v m="$1" -v k="$margin" 'BEGIN { s = m - k; if (s < m / 2) s = m / 2; printf "%.2f", s }'; }

LEVEL=${WIDE_LEVEL:-S1.5,S2.5} LR=${WIDE_LR:-3e-4} WARMUP=150 \
  ./gpu_finetune.sh "$out/a" "$wide" "$(schedule "$wide")" || exit 1
tuned=$(ls -v "$out"/a/weights-step*.pth 2>/dev/null | tail -n 1)
[ -n "$tuned" ] || { echo "the wide-scale run saved no weights" >&2; exit 1; }
mix=/tmp/posematch-mix.pth
python3 interpolate.py --base data/init.safetensors --tuned "$tuned" --alpha "${ALPHA:-0.5}" \
  --out "$mix" 2>&1 | tee -a "$out/a/log.txt" || exit 1
INIT=$mix LEVEL=${COOL_LEVEL:-S1.5} LR=${COOL_LR:-1e-4} WARMUP=50 CROWD=${COOL_CROWD:-$CROWD} \
  ./gpu_finetune.sh "$out/b" "$cool" "$(schedule "$cool")"
