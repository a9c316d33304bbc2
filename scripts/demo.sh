#!/usr/bin/env bash
# Installs votesplat_ns into ./.venv, trains it on the bundled demo scene (GPU if present,
# else CPU), exports the instances and prints where everything is.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh

if .venv/bin/python -c 'import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)'; then
  device=cuda; steps=${STEPS:-3000}; vote_every=4
else
  # on a CPU the colour pass dominates a step, and 1000 steps leave few vote steps: vote every step
  device=cpu; steps=${STEPS:-1000}; vote_every=1
fi
run_dir=outputs/demo/votesplat/demo
echo "training votesplat on the demo scene: $steps steps on $device"
.venv/bin/ns-train votesplat --data votesplat_ns/data/demo \
  --machine.device-type "$device" --max-num-iterations "$steps" \
  --pipeline.model.vote-start-step 200 --pipeline.model.vote-every-n-steps "$vote_every" \
  --pipeline.model.num-downscales 0 \
  --steps-per-eval-all-images 100000 --vis tensorboard \
  --output-dir outputs --experiment-name demo --timestamp demo
.venv/bin/ns-export votesplat-instances --load-config "$run_dir/config.yml" --output-dir outputs/demo/instances
cat <<MSG

Done.
  trained model : $run_dir/config.yml
  instances     : outputs/demo/instances  (one 3DGS PLY per instance, instances.json, instances.png)
  look at it    : .venv/bin/ns-viewer --load-config $run_dir/config.yml
MSG
