#!/usr/bin/env bash
# Short runs at equal pairs before the long run (issue: model choice and the Sinkhorn-gradient
# A/B), all on one fixed pre-generated pool so that every run sees the same batches:
#   python training/generate_pairs.py --pool training/runs/short_pool --seed 100 --shards 12 --max-pending 1000
#   bash training/compare_configs.sh            # then: python training/summarize_runs.py training/runs/compare/*
# Runs in parallel, one thread each.
set -euo pipefail
cd "$(dirname "$0")"
PAIRS=${PAIRS:-1536}
common=(--fixed-pool runs/short_pool --pairs "$PAIRS" --warmup 400 --keypoints 512x8:1 --val-every "$PAIRS"
        --val-pairs 128 --threads 1 --lr 5e-4)
run() { local name=$1; shift; python train.py --run "runs/compare/$name" --work "runs/compare/$name" "${common[@]}" "$@" \
          > "runs/compare/$name.log" 2>&1; }
mkdir -p runs/compare
run c64h4_last --dim 64 --heads 4 --sinkhorn-grad last &
run c64h4_full --dim 64 --heads 4 --sinkhorn-grad full &
run c64h2_last --dim 64 --heads 2 --sinkhorn-grad last &
run c96h2_last --dim 96 --heads 2 --sinkhorn-grad last &
wait
