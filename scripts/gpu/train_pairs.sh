#!/bin/bash
# Splatfacto and votesplat trained side by side, $PAIRS pairs at once (default 2) on one GPU, each run with the
# step timer: the two methods share the machine's state (clocks, caches, other load) instead of running one
# after the other, where run order alone moved the ratio by ±0.05. Run on the device after
# `bash scripts/gpu/run.sh setup`, with the data carried:
#   bash scripts/gpu/run.sh setup && bash scripts/gpu/train_pairs.sh synthetic build/family_test/family_2054
#   bash scripts/gpu/run.sh setup && bash scripts/gpu/train_pairs.sh fox
# STEPS (3000), EXTRA_TRAIN_ARGS and VOTESPLAT_TRAIN_ARGS as for run.sh (default: votes every step, full
# resolution from the start). Writes $OUT/pairs_<stage>_p<k>_<method>.json (step times) and prints each pair's
# comparison (benchmarks/step_times.py).
stage=${1:?train_pairs.sh: pass synthetic [DATA] or fox}; shift
export STEPS=${STEPS:-3000} VOTESPLAT_STEP_TIMES=1
export EXTRA_TRAIN_ARGS=${EXTRA_TRAIN_ARGS:-"--pipeline.model.num-downscales 0"}
export VOTESPLAT_TRAIN_ARGS=${VOTESPLAT_TRAIN_ARGS:-"--pipeline.model.vote-every-n-steps 1"}
OUT=${OUT:-/tmp/votesplat_gpu_out}
work=/tmp/train_pairs
rm -rf "$work"
for k in $(seq "${PAIRS:-2}"); do
  for method in splatfacto votesplat; do
    mkdir -p "$work/p$k/$method"
    RUNS=$work/p$k/$method/runs OUT=$work/p$k/$method METHODS=$method \
      bash scripts/gpu/run.sh "train-$stage" "$@" >"$work/p$k/$method/run.log" 2>&1 &
  done
done
wait
for k in $(seq "${PAIRS:-2}"); do
  for method in splatfacto votesplat; do
    cp "$work/p$k/$method/steps_${stage}_$method.json" "$OUT/pairs_${stage}_p${k}_$method.json" || tail -5 "$work/p$k/$method/run.log"
  done
  echo "== pair $k"
  python3 benchmarks/step_times.py "$OUT/pairs_${stage}_p${k}_splatfacto.json" "$OUT/pairs_${stage}_p${k}_votesplat.json" \
    --ranges 0:1 1:20 20:500 500:520 520:"$STEPS" | grep -v '^      '
  grep -h '"psnr"' "$work/p$k"/*/train_"$stage".json | head -2
done
