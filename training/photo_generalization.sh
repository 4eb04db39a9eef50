#!/usr/bin/env bash
# Does the model memorise its 380 training photos? Scores matchers on two synthetic pools
# built the same way (same seed, same recipe, no real pairs) that differ only in the photos:
# train/bsds500_train (trained on) and train/bsds500_val (never trained on; the holdout's
# photos), both BSDS500 at 481x321. A gap on the learned models that mutual NN and
# LighterGlue (never trained on either) do not show would be memorisation.
#   bash training/photo_generalization.sh LABEL=WEIGHTS.safetensors@THRESHOLD ...
# Writes training/results/photo_generalization_<photos>_<keypoints>kp.json, or ..._<TAG>.json
# with TAG set in the environment (to keep an earlier run's files).
set -euo pipefail
cd "$(dirname "$0")"
shared=../../shared/data/train
matchers=()
for m in "$@"; do matchers+=(--matcher "$m"); done
for photos in bsds500_train bsds500_val; do
  pool=cache/photo_generalization/$photos
  [ -f "$pool/shard_000000.npz" ] || RAYON_NUM_THREADS=1 python generate_pairs.py --pool "$pool" --seed 77 \
      --shards 1 --shard-size 128 --max-pending 1000 --photos "$shared/$photos" --real-fraction 0
  for k in 512 2048; do
    python holdout_peers.py --holdout "$pool" --keypoints "$k" --threads "${THREADS:-1}" --lighterglue \
        --ransac-seeds 3 "${matchers[@]}" --json "results/photo_generalization_${photos}_${k}kp${TAG:+_$TAG}.json"
  done
done
