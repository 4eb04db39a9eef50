#!/usr/bin/env bash
# The long training of a shipped model, resumable anywhere: the committed checkpoint
# (training/checkpoints/NAME/last.pt, weights + optimiser + stream cursor) is the state; the
# pairs regenerate from seeds. Run (and rerun after any stop, on this or a fresh machine):
#   nohup nice -n 10 bash training/train_shipped.sh paraformer-xfeat > training/runs/paraformer-xfeat.log 2>&1 &
# Extra arguments go to train.py (e.g. --stop-after 300000). The model arguments below must
# not change for a run in progress (train.py refuses a checkpoint of other model arguments).
set -euo pipefail
cd "$(dirname "$0")"
name=${1:?usage: train_shipped.sh paraformer-xfeat|paraformer-u-xfeat|paraformer-xfeat-w96|paraformer-xfeat-w96-d6|paraformer-u-xfeat-w96 [train.py arguments]}
shift
case "$name" in
  paraformer-xfeat)   model=(--preset paraformer --dim 64 --heads 2 --depth 4); pairs=100000 ;;
  paraformer-u-xfeat) model=(--preset paraformer_u --dim 64 --heads 2 --depth 4); pairs=100000 ;;
  # The next paraformer-xfeat (exported under that name once it wins): width 96, 3 heads of
  # width 32, from scratch; compare_capacity.sh showed it ahead of width 64 at equal pairs.
  paraformer-xfeat-w96) model=(--preset paraformer --dim 96 --heads 3 --depth 4); pairs=300000 ;;
  # The w96 line grown to 6 layers (--init of its 4-layer weights: layers 4 and 5 start as
  # identity). The engine's speed-ups since the 4-layer choice put 6 layers at 0.39 of
  # LighterGlue's latency in bf16 (training/README "Six layers"). Without --init it trains from
  # scratch (checkpoints/paraformer-xfeat-w96-d6-scratch, README "Six layers from scratch").
  paraformer-xfeat-w96-d6) model=(--preset paraformer --dim 96 --heads 3 --depth 6); pairs=600000 ;;
  # Its U-Net sibling, started with --init from the w96 line: the outer stages take its
  # layers 0 and 2 (train.py u_from_paraformer). Widths 96, 96, 48, 96, 96 and gPool, not the
  # paper's scaled 96, 144, 48, 144, 96 and attentional pooling: in the engine at 2048
  # keypoints (bf16, random weights, one alternated run) they cost 74.6 ms against 82.0 and
  # 94.9, the w96 ParaFormer 90.4 (training/README "ParaFormer-U at width 96").
  paraformer-u-xfeat-w96) model=(--preset paraformer_u --dim 96 --heads 3 --depth 4 --stage-dims 96 96 48 96 96
                                 --pooling gpool); pairs=300000 ;;
  *) echo "unknown model $name" >&2; exit 2 ;;
esac
mkdir -p runs
# libgomp's idle threads spin for ~300k iterations after each PyTorch op by default; with
# --native-attention the engine's own (rayon) threads run between those ops and lose a core
# to the spinning. 20,000 measured best (bench_step.py, w96, --native-attention: 0.389 ->
# 0.299 s at 512 x 8, 0.668 -> 0.550 at 1024 x 4, 0.849 -> 0.785 at 2048 x 2; PASSIVE between).
export GOMP_SPINCOUNT=${GOMP_SPINCOUNT:-20000}
# glibc hands blocks above its mmap threshold back to the kernel and trims the heap's top, so
# each step faults in its large buffers afresh (the native attention's byte buffers, the
# 2049 x 2049 couplings). Keeping them: 0.689-0.770 -> 0.570-0.581 s per native step at
# 2048 x 2, unchanged at 512 x 8 (bench_step.py, three alternated rounds of separate processes).
# The mmap threshold above glibc's mallopt cap (32 MiB) still takes effect through the
# environment on glibc 2.36: scripts/malloc_reuse_probe.py 600 40 touches a 600 MiB block
# with 0 faults after the first only with it (153,600 every time with trim + top pad alone).
export MALLOC_MMAP_THRESHOLD_=${MALLOC_MMAP_THRESHOLD_:-4000000000}
export MALLOC_TRIM_THRESHOLD_=${MALLOC_TRIM_THRESHOLD_:-4000000000}
export MALLOC_TOP_PAD_=${MALLOC_TOP_PAD_:-268435456}
# --pairs sets the learning-rate schedule: constant, then cosine to 10% from 60% of it. For
# the 64-wide runs it was 400,000 until 50,000 pairs; validation had been flat since 10,000
# (F1@512 0.51-0.54) at the constant rate, so they anneal at 60,000-100,000.
# --bf16: the forward under bfloat16 autocast, 1.16-1.26x pairs/s (bench_step.py) at equal
# validation loss (compare_capacity.sh arm wide_bf16); the w96 run uses it from pair 5,432.
# --ema-warmup: the w96 run started from scratch with a fixed EMA decay of 0.999, whose
# weights at 10,002 pairs were still 19% random init (val loss @512 1.751 against the trained
# weights' 1.237); from pair ~10,300 the decay rises from 0.995 to 0.999 instead.
exec python train.py --run "checkpoints/$name" "${model[@]}" --sinkhorn 50 --pairs "$pairs" \
  --keypoints 512x8:0.55,1024x4:0.3,2048x2:0.15 --lr 5e-4 --warmup 4000 --ckpt-minutes 10 --val-every 10000 \
  --bf16 --ema-warmup "$@"
