#!/bin/bash
# Trainings side by side on one GPU, each through run.sh (its flags, launcher, step timer and ns-eval), so that
# the runs compared share the machine's state (one after the other, run order alone moved a ratio by ±0.05).
# Run on the device after `bash scripts/gpu/run.sh setup`, with the data carried:
#   bash scripts/gpu/train_side_by_side.sh synthetic build/family_test/family_2054    # cost: two pairs at seed 42
#   SEEDS="3 4 5" TRAININGS="splatfacto splatfacto every1" bash scripts/gpu/train_side_by_side.sh fox   # PSNR
# STAGE: run.sh's train-<stage> (synthetic [DATA] or fox). SEEDS (default "42 42"): one group of trainings per
# entry, at that --machine.seed. TRAININGS (default "splatfacto votesplat"), the trainings of a group:
# splatfacto, votesplat (with VOTESPLAT_TRAIN_ARGS, default votes every step), every1 or every4 (votesplat
# voting every step / every 4th step). Splatfacto twice at one seed measures gsplat's run-to-run noise (its
# backward adds gradients atomically). STEPS (3000) and EXTRA_TRAIN_ARGS (default: full resolution from the
# start) as for run.sh; four trainings at once slow every step, so read absolute per-step increments, not ratios.
# Prints, per group, benchmarks/step_times.py on its first two trainings; copies
# the step times to $OUT/side_<stage>_g<group>_<k>_<training>.json (8 files come back from a call). Then the PSNR
# table of benchmarks/psnr_seeds.py (each training against its group's first: per group, then the mean difference
# over the groups with its standard error), also as $OUT/psnr_side_<stage>.json. A PSNR difference of 0.1 dB needs
# many seeds (SEEDS="42 7 1 2 ..."): two runs of one seed differ by 0.3-3.7 dB. STEP_TIMES=0 (for such PSNR-only
# calls) runs without the step timer and copies no step files, so that psnr_side_<stage>.json is among the 8.
# `python benchmarks/psnr_seeds.py --pool` over several calls' psnr_side_<stage>.json gives the table over all their seeds.
stage=${1:?train_side_by_side.sh: pass synthetic [DATA] or fox}; shift
export STEPS=${STEPS:-3000}
if [ "${STEP_TIMES:-1}" = 0 ]; then export VOTESPLAT_STEP_TIMES=; else export VOTESPLAT_STEP_TIMES=1; fi
EXTRA_TRAIN_ARGS=${EXTRA_TRAIN_ARGS:-"--pipeline.model.num-downscales 0"}
OUT=${OUT:-/tmp/votesplat_gpu_out}
mkdir -p "$OUT"
for training in ${TRAININGS:-splatfacto votesplat}; do  # all checked before any starts
  case $training in splatfacto|votesplat|every1|every4) ;;
    *) echo "TRAININGS: unknown training $training (splatfacto, votesplat, every1, every4)" >&2; exit 2 ;;
  esac
done
work=${WORK:-/tmp/train_side_by_side}  # set it (and OUT) apart to run two of these at once
rm -rf "$work"
group=0
for seed in ${SEEDS:-42 42}; do
  group=$((group + 1)) k=0
  for training in ${TRAININGS:-splatfacto votesplat}; do
    k=$((k + 1)) method=votesplat vote_args=
    case $training in
      splatfacto) method=splatfacto ;;
      votesplat) vote_args=${VOTESPLAT_TRAIN_ARGS:-"--pipeline.model.vote-every-n-steps 1"} ;;
      every1) vote_args="--pipeline.model.vote-every-n-steps 1" ;;
      every4) vote_args="--pipeline.model.vote-every-n-steps 4" ;;
    esac
    dir=$work/g$group-seed$seed/${k}_$training
    mkdir -p "$dir"
    RUNS=$dir/runs OUT=$dir METHODS=$method VOTESPLAT_TRAIN_ARGS=$vote_args \
      EXTRA_TRAIN_ARGS="$EXTRA_TRAIN_ARGS --machine.seed $seed" \
      bash scripts/gpu/run.sh "train-$stage" "$@" >"$dir/run.log" 2>&1 &
  done
done
wait
for folder in "$work"/g*-seed*; do
  g=${folder##*/} && g=${g%%-*} && g=${g#g}
  echo "== group $g"
  steps=()
  for dir in "$folder"/*/; do
    dir=${dir%/} name=${dir##*/}
    for file in "$dir"/steps_*.json; do
      [ -f "$file" ] || continue
      cp "$file" "$OUT/side_${stage}_g${g}_$name.json" && steps+=("$OUT/side_${stage}_g${g}_$name.json")
    done
  done
  [ "${#steps[@]}" -ge 2 ] && python3 benchmarks/step_times.py "${steps[0]}" "${steps[1]}" \
    --ranges 0:1 1:20 20:500 500:520 520:"$STEPS" | grep -v '^      '
done
echo "== eval PSNR, each training against its group's first"
python3 benchmarks/psnr_seeds.py "$work"/g*-seed* --json "$OUT/psnr_side_$stage.json"
