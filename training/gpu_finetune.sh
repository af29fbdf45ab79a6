#!/usr/bin/env bash
# Bounded GPU calls: measure, then fine-tune the shipped default, writing what comes back into
# OUT (log.txt, profile.txt and the weights of every save, weights-step<N>.pth: the last is the
# run's end).
#
#   training/gpu_finetune.sh OUT MINUTES [SCHEDULE_MINUTES]     first call: measure and train
#   RESUME=1 training/gpu_finetune.sh OUT MINUTES               a later call on the warm machine
#
# The first call profiles three eager steps (profile.txt), measures eager and compiled steps
# (batch 1024, 160x160), trains MINUTES with the faster, and sets --steps to what the measured
# rate reaches in SCHEDULE_MINUTES (default MINUTES) so that the cosine schedule ends at its
# floor when the last call's time is up. The run itself lives in RUN (default
# /tmp/posematch-gpu-run: checkpoint.pt every 2 minutes), outside the repository, so a RESUME call
# on the same warm machine continues it: a path named in the device tool's `carry` is replaced
# by this machine's copy on every call, which lost a run kept in training/data/run (2026-11-26).
#
# Needs training/data/corpus (make_corpus.py) and training/data/init.safetensors
# (`posematch weights export --out training/data/init.safetensors`) beside it. The mix is set
# by LEVEL (default S1.5), ELONGATED (share, 0.5), ASPECT (largest sx/sy, 2.2), CROWD (share of
# crowded pairs, 0), LR (3e-4),
# WARMUP (150), BATCH (1024), MODES (eager,compile); INIT=none trains afresh from random
# initialisation instead (then e.g. LR=1e-3 WARMUP=500, as the base run). MEASURE=0 skips the
# measurement and plans with RATE (default 3074, the H200's compiled rate of 2026-11-26) in the
# first of MODES (then MODES=compile): a lease's minutes go to training. FIT=1 lets train.py
# re-plan --steps from its own rate inside the warm-up (--fit-schedule SCHEDULE_MINUTES), so that
# a wrong RATE neither stops the schedule early nor leaves it above its floor.
set -u
out=${1:?OUT folder}
minutes=${2:?training minutes}
schedule=${3:-$minutes}
here=$(cd "$(dirname "$0")" && pwd)
cd "$here"
run=${RUN:-/tmp/posematch-gpu-run}
mkdir -p "$out" "$run"
export PYTHONUNBUFFERED=1
log="$out/log.txt"
level=${LEVEL:-S1.5} elongated=${ELONGATED:-0.5} aspect=${ASPECT:-2.2}
lr=${LR:-3e-4} warmup=${WARMUP:-150} batch=${BATCH:-1024} modes=${MODES:-eager,compile}
crowd=${CROWD:-0}

if [ -z "${RESUME:-}" ]; then
  rm -rf "$run" && mkdir -p "$run"   # a first call starts a new run
  nvidia-smi --query-gpu=name,memory.total,clocks.sm --format=csv 2>&1 | tee "$log"
  if [ "${MEASURE:-1}" = 0 ]; then   # the rate is known (RATE pairs/s in MODES' first mode)
    echo "$batch 160 ${RATE:-3074} ${modes%%,*}" > "$run"/choose.txt
  else
    timeout 240 python3 measure.py --corpus data/corpus --batches "$batch" --sizes 160 \
      --modes "$modes" --profile "$out/profile.txt" --choose "$run"/choose.txt 2>&1 | tee -a "$log"
  fi
  if read -r chosen_batch size rate mode < "$run"/choose.txt 2>/dev/null && [ -n "${mode:-}" ]; then :; else
    chosen_batch=$batch size=160 rate=2192 mode=eager   # the last run's measured rate, should measuring fail
  fi
  rate=${rate%.*}
  steps=$(awk -v r="$rate" -v m="$schedule" -v b="$chosen_batch" 'BEGIN { printf "%d", r * m * 60 / b }')
  echo "$chosen_batch $size $steps $mode" > "$run"/plan.txt
  echo "batch $chosen_batch crop $size rate $rate pairs/s ($mode) -> steps $steps over $schedule min" | tee -a "$log"
  init=${INIT:-data/init.safetensors}
  if [ "$init" = none ]; then start=(); else start=(--init-weights "$init"); fi
else
  read -r chosen_batch size steps mode < "$run"/plan.txt
  echo "resume: batch $chosen_batch crop $size steps $steps ($mode)" | tee -a "$log"
  start=(--resume)
fi
compile=()
[ "$mode" = compile ] && compile=(--compile)
fit=()
[ "${FIT:-0}" = 1 ] && [ -z "${RESUME:-}" ] && fit=(--fit-schedule "$schedule")

python3 train.py --corpus data/corpus --out "$run" "${start[@]}" "${compile[@]}" "${fit[@]}" \
  --elongated-share "$elongated" --aspect-max "$aspect" --level "$level" --crowd-share "$crowd" \
  --steps "$steps" --batch "$chosen_batch" --search-size "$size" --lr "$lr" --warmup "$warmup" \
  --minutes "$minutes" --save-every 2 --snapshots "$out" --validate-every 400 --log-every 50 \
  2>&1 | tee -a "$log"
# What the weights were trained on (posematch weights import --trained-on), to the last save.
cp "$run/trained_on.json" "$out/" 2>/dev/null
ls -la "$out"
