#!/usr/bin/env bash
# What limits the 2-head line: fine-tunes of one checkpoint at equal pairs, one after the
# other on one fixed pre-generated pool (same batches, same order), each a change that could
# lift the plateau: gradients through all Sinkhorn iterations, a loss on every layer
# (training-only heads), two more layers (grown as identity layers, so every arm starts from
# the same function), both of the last two, and separate self/cross q/k/v and merges (equal
# copies of the shared ones at the start: again the same function). Generate the pool once, then run:
#   python training/generate_pairs.py --pool training/runs/finetune_pool --seed 300 --shards 40 \
#       --max-pending 1000 --real-fraction 0.5
#   bash training/compare_finetunes.sh     # PAIRS=3600 ARMS="control layer_loss" to choose
# The width-96 line's plateau (training/README "Relative positions in self-attention"):
#   OUT=runs/compare_finetunes_w96 INIT=checkpoints/paraformer-xfeat-w96-alpha025/last.pt DIM=96 HEADS=3 \
#       POSITIVE_PX= ARMS="control self_rotary" bash training/compare_finetunes.sh
# Each arm's log.jsonl lands in training/runs/compare_finetunes/<arm>/; the initial weights'
# validation in .../init/. Summary: python training/summarize_runs.py training/runs/compare_finetunes/*
set -euo pipefail
cd "$(dirname "$0")"
PAIRS=${PAIRS:-3600}
KEYPOINTS=${KEYPOINTS:-512x8:0.75,1024x4:0.25}
INIT=${INIT:-checkpoints/paraformer-xfeat-finetune-1p5px-cont/last.pt}
ARMS=${ARMS:-"control full_sinkhorn_grad layer_loss depth6 depth6_layer_loss"}
OUT=${OUT:-runs/compare_finetunes}
POSITIVE_PX=${POSITIVE_PX-1.5}  # empty: train.py's default positives (the w96 line's)
common=(--preset paraformer --dim "${DIM:-64}" --heads "${HEADS:-2}" --init "$INIT" --fixed-pool runs/finetune_pool
        --pairs "$PAIRS" --keypoints "$KEYPOINTS" --lr 1e-4 --warmup 200 --ema 0.99 --val-every $((PAIRS / 2))
        --real-fraction 0.5 --seed 11 --threads "${THREADS:-2}")
if [ -n "$POSITIVE_PX" ]; then common+=(--synthetic-positive-px "$POSITIVE_PX"); fi
mkdir -p "$OUT"
# The initial weights' validation, redone when OUT was last used with another INIT.
if [ ! -s "$OUT/init/log.jsonl" ] || [ "$(cat "$OUT/init/INIT" 2>/dev/null)" != "$INIT" ]; then
  rm -rf "$OUT/init"
  python train.py --run "$OUT/init" --work "$OUT/init" "${common[@]}" --depth 4 --validate-only > "$OUT/init.log" 2>&1
  echo "$INIT" > "$OUT/init/INIT"
fi
for arm in $ARMS; do
  case $arm in
    control) extra=(--depth 4) ;;
    full_sinkhorn_grad) extra=(--depth 4 --sinkhorn-grad full) ;;
    layer_loss) extra=(--depth 4 --layer-loss) ;;
    depth6) extra=(--depth 6) ;;
    depth6_layer_loss) extra=(--depth 6 --layer-loss) ;;
    unshared) extra=(--depth 4 --unshare qkv merge) ;;
    # Outside the SPEC: rotary self-attention added to a trained model, its angles starting at
    # zero (the same function at the start) and growing at 10x Adam's step.
    self_rotary) extra=(--depth 4 --self-rotary 1 100 10) ;;
    # The same recipe on a pool without real pairs (generate_pairs.py --pool
    # runs/finetune_pool_synthetic --seed 300 --shards 40 --max-pending 1000 --real-fraction 0):
    # whether the real pairs' labels cost the synthetic matching at the plateau.
    synthetic_only) extra=(--depth 4 --fixed-pool runs/finetune_pool_synthetic) ;;
    *) echo "unknown arm $arm" >&2; exit 2 ;;
  esac
  python train.py --run "$OUT/$arm" --work "$OUT/$arm" "${common[@]}" "${extra[@]}" > "$OUT/$arm.log" 2>&1
done
