#!/bin/bash
# The fox's PSNR spread across seeds: splatfacto and votesplat (votes every step, and the default every 4th
# step) at the seeds in $SEEDS (default "1 2"), side by side on one GPU, each scored by ns-eval. $RUNS picks
# the runs per seed (default "sf every1 every4"; "sf2" is splatfacto again at the same seed: gsplat's backward
# adds gradients atomically, so two runs of one seed differ, and sf2 - sf is that noise). Run on the device
# after `bash scripts/gpu/run.sh setup` (it writes /tmp/ns_launch.py), with .gpu/fox carried:
#   bash scripts/gpu/run.sh setup && bash scripts/gpu/fox_psnr_seeds.sh
export PYTHONPATH=$PWD:/tmp/site PATH=/tmp/site/bin:$PATH TORCH_EXTENSIONS_DIR=/tmp/torch_extensions \
  GSPLAT_PREBUILT_SO=/tmp/torch_extensions/gsplat_cuda/gsplat_cuda.so MPLBACKEND=Agg OMP_NUM_THREADS=2
R=/tmp/psnr; mkdir -p $R
one() {  # name method seed extra...
  local name=$1 method=$2 seed=$3; shift 3
  local vote=()
  [ "$method" = votesplat ] && vote=(--pipeline.datamanager.mask-source folder --pipeline.datamanager.mask-folder .gpu/fox/votesplat_masks
    --pipeline.datamanager.mask-levels coarse fine --pipeline.model.vote-levels coarse fine --pipeline.datamanager.cache-dir $R/cache_$name)
  timeout 420 python3 /tmp/ns_launch.py train $method --data .gpu/fox --max-num-iterations 3000 --vis tensorboard \
    --viewer.quit-on-train-completion True --output-dir $R --experiment-name $name --timestamp run --machine.seed $seed \
    "${vote[@]}" --pipeline.model.num-downscales 0 "$@" nerfstudio-data --downscale-factor 2 > $R/$name.log 2>&1
  timeout 120 python3 /tmp/ns_launch.py eval --load-config $R/$name/$method/run/config.yml --output-path $R/eval_$name.json >> $R/$name.log 2>&1
  python3 -c "import json,sys; d=json.load(open('$R/eval_$name.json'))['results']; print('$name', round(d['psnr'],3), round(d['ssim'],4))" || echo "$name failed"
}
for s in ${SEEDS:-1 2}; do
  for run in ${RUNS:-sf every1 every4}; do
    case $run in
      sf|sf2) one ${run}_s$s splatfacto $s & ;;
      every1) one every1_s$s votesplat $s --pipeline.model.vote-every-n-steps 1 & ;;
      every4) one every4_s$s votesplat $s & ;;
      *) echo "RUNS: unknown run $run (sf, sf2, every1, every4)"; exit 2 ;;
    esac
  done
done
wait
