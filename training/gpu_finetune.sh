#!/usr/bin/env bash
# One bounded GPU call: measure, then fine-tune the shipped default on elongated and
# wide-scale pairs, writing the run into OUT (checkpoint.pt, weights.pth, log.txt).
#
#   training/gpu_finetune.sh OUT MINUTES
#
# Needs training/data/corpus (make_corpus.py) and training/data/init.safetensors
# (`posematch weights export --out training/data/init.safetensors`) beside it. The batch is the
# faster of 512 and 1024 at 160x160 by measure.py; --steps is what the measured rate reaches in
# MINUTES, so that the cosine schedule ends at its floor when the time is up.
set -u
out=${1:?OUT folder}
minutes=${2:?training minutes}
here=$(cd "$(dirname "$0")" && pwd)
cd "$here"
mkdir -p "$out"
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,clocks.sm --format=csv | tee "$out/gpu.txt"

timeout 90 python3 measure.py --corpus data/corpus --batches 512,1024 --sizes 160 \
  --choose "$out/choose.txt" 2>&1 | tee "$out/measure.txt"
if read -r batch size rate < "$out/choose.txt" 2>/dev/null && [ -n "${rate:-}" ]; then :; else
  batch=512 size=160 rate=1888   # the last run's measured rate, should measuring fail
fi
rate=${rate%.*}
steps=$(( rate * ${minutes%.*} * 60 / batch ))
echo "batch $batch crop $size rate $rate pairs/s -> steps $steps" | tee -a "$out/measure.txt"

python3 train.py --corpus data/corpus --out "$out/run" --init-weights data/init.safetensors \
  --elongated-share 0.5 --aspect-max 2.5 --level S1.5,S2.5 \
  --steps "$steps" --batch "$batch" --search-size "$size" --lr 5e-4 --warmup 150 \
  --minutes "$minutes" --save-every 2 --validate-every 400 --log-every 50
