#!/usr/bin/env bash
# Whole training run of the issue-7 comparison, resumable: rerun the same command after a
# stop and every step continues where it was (dataset shards are skipped when present,
# trainings resume from <run>/last.pt). Runs in the background:
#   nohup bash training/run_all.sh > training/runs/run_all.log 2>&1 &
# Settings (environment): STEPS, DIM, DEPTH, BATCH, LR, THREADS, TRAIN_PAIRS.
set -euo pipefail
cd "$(dirname "$0")/.."
SHARED=${SHARED:-../shared/data}
STEPS=${STEPS:-1000}; DIM=${DIM:-64}; DEPTH=${DEPTH:-4}; BATCH=${BATCH:-8}; LR=${LR:-1e-3}
THREADS=${THREADS:-2}; TRAIN_PAIRS=${TRAIN_PAIRS:-8000}
mkdir -p training/runs
# Training photos: train/* except bsds500_val, which is held out for the in-training validation.
python training/make_dataset.py --photos "$SHARED/train/bsds500_train" "$SHARED/train/urban100" "$SHARED/train/sun80" \
  --out training/cache/train --count "$TRAIN_PAIRS" --seed 0 --threads "$THREADS"
python training/make_dataset.py --photos "$SHARED/train/bsds500_val" --out training/cache/holdout --count 300 --seed 1 \
  --threads "$THREADS"
for preset in ${PRESETS:-paraformer paraformer_u superglue parallel_mlp}; do
  python training/train.py --preset "$preset" --dim "$DIM" --depth "$DEPTH" --batch "$BATCH" --lr "$LR" \
    --steps "$STEPS" --warmup 100 --val-every 100 --threads "$THREADS" \
    --data training/cache/train --val training/cache/holdout --out "training/runs/$preset"
done
echo "all trainings done"
