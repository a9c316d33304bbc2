#!/usr/bin/env bash
# The one entry for the lent GPU machine (no internet there; see scripts/gpu/README.md):
#
#   bash scripts/gpu/run.sh STAGE [STAGE ...]        e.g.  setup tests bench-vote
#
# Stages (expected wall time on one H100; every stage after `setup` runs `setup` first if this
# machine has not been set up, so each call can stand alone on a fresh machine):
#   setup             ~30 s with .gpu/gsplat_build.tar.gz carried, ~240 s without (gsplat's
#                     CUDA JIT build, ~200 s; the fresh build comes back as $OUT/gsplat_build.tar.gz)
#   tests             ~60 s + ~1-2 min of Triton JIT builds for test_vote_fused.py: pytest of $GPU_TESTS
#                     (CUDA-only tests run here, skipped on CPU)
#   bench-vote        ~100-200 s  benchmarks/bench_vote_render.py at 500k@1440x1080 and 100k@720x540:
#                     RGB pass, torch vote pass and the Triton kernels ($KERNEL_CONFIGS), first-call
#                     JIT time from an empty Triton cache, peak memory, ratios to the RGB pass
#   train-fox         one training per method of $METHODS on the fox, with ns-eval after it: what train-balanced
#                     and scripts/gpu/train_side_by_side.sh run for each of their trainings (STEPS=7000:
#                     splatfacto ~215 s; run the methods as separate calls to stay under the 600 s limit)
#   train-synthetic [DATA]  the same on a synthetic scene (default .gpu/synthetic, masks from its transforms.json)
#   quality           ~300-450 s  benchmarks/quality.py on the scenes in $QUALITY_SCENES (GT and
#                     noisy masks) and the ablation on $ABLATION_SCENE (each seed of $ABLATION_SEEDS,
#                     then mean ± std), every run its own process,
#                     all at once (the GPU is mostly idle in one small-scene run); QUALITY_STEPS
#                     (3000), QUALITY_VOTE_START (500). Output quality.md (merged tables), quality.tar.gz
#   sweep             benchmarks/sweep.py: training x clustering variants on $SWEEP_SCENES, or on a
#                     (SWEEP_TAG=x: work folder and returned files sweep_x.*, for parallel sweeps)
#                     family set with SWEEP_ARGS="--family test --family-dir build/family_test ..."
#                     (carry the set's folder), all trainings in parallel worker processes (--jobs);
#                     sweep.md, sweep.json, sweep.log. 12 runs of 3000 steps at 256x192: ~290 s
#   train-balanced fox|synthetic [DATA]  splatfacto and votesplat timed in the order $ORDER (default
#                     "splatfacto votesplat votesplat splatfacto"), after a throwaway $WARM_UP_STEPS-step (50)
#                     splatfacto run that takes the machine's first-training cost (~4 s more at step 0); each run
#                     with its own folders and empty Triton cache and VOTESPLAT_STEP_TIMES (BALANCED_STEP_TIMES:
#                     walls, or 1 for the phases too, which charge votesplat's more wrapped calls), the time left shared
#                     among the runs left. After each run $OUT/balanced_<experiment>.md (benchmarks/step_times.py
#                     --table: a row per run, votesplat's means over splatfacto's) and .tar.gz (the runs' files)
#                     are written again, so a call cut short keeps the runs it finished. 4 runs: ~300-450 s
#
# A call never runs past CALL_BUDGET_S (default 570 s from its start): a training run gets the
# time left minus an eval reserve, and one cut short is reported as "timeout" (what it wrote
# still comes back). Outputs, at most 8 files in $OUT per call:
#   setup.log, gsplat_build.tar.gz (fresh builds only), tests.log, bench_vote.log,
#   train_fox.json + train_fox.log, train_synthetic.json + train_synthetic.log
#
# Environment: STEPS (7000), METHODS ("splatfacto votesplat"), CALL_BUDGET_S (570),
# GPU_TESTS, KERNEL_CONFIGS, SYNTH_DOWNSCALE (1), FOX (.gpu/fox), PY (python3), EXTRA_TRAIN_ARGS (both methods),
# EVAL (1; 0 skips the ns-eval after each training, for runs that only time the training).
# VOTESPLAT_STEP_TIMES=1 writes every step's wall and phase host times of each ns-train, no profiler,
# into $OUT/steps_<experiment>_<method>.json (set-up and tail too; compare with benchmarks/step_times.py);
# VOTESPLAT_STEP_TIMES=walls the steps' walls only (no wrapper around the phases: what train-balanced times).
set -uo pipefail
cd "$(dirname "$0")/../.." || exit 2

# --- votesplat's CLI flags (owned by votesplat_ns/ns/datamanager.py and model.py; update here if
# --- they are renamed) --------------------------------------------------------------------
VOTE_MASK_SOURCE_FLAG=--pipeline.datamanager.mask-source
VOTE_MASK_FOLDER_FLAG=--pipeline.datamanager.mask-folder
VOTE_MASK_LEVELS_FLAG=--pipeline.datamanager.mask-levels
VOTE_CACHE_DIR_FLAG=--pipeline.datamanager.cache-dir
MODEL_VOTE_LEVELS_FLAG=--pipeline.model.vote-levels
FOX_MASK_LEVELS=(coarse fine)          # sub-folders written by scripts/gpu/prepare_fox.py
SYNTH_MASK_LEVELS=(instance part)      # <level>_mask_path keys of the synthetic scenes

STEPS=${STEPS:-7000}
METHODS=${METHODS:-"splatfacto votesplat"}
CALL_BUDGET_S=${CALL_BUDGET_S:-570}
EVAL_RESERVE_S=${EVAL_RESERVE_S:-45}
GPU_TESTS=${GPU_TESTS:-"tests/test_vote_render.py tests/test_vote_fused.py tests/test_rasterize_torch.py tests/test_viewer.py"}
# Triton kernel variants (walk block width x warps per program) that bench-vote times next to the torch vote pass
KERNEL_CONFIGS=${KERNEL_CONFIGS:-"32x2 32x4 16x1 64x4"}
# the vote pass implementations bench-vote times: the training step's path (triton-sampled) by default
BENCH_VOTE_BACKENDS=${BENCH_VOTE_BACKENDS:-"torch triton-fused triton-sampled"}
BENCH_VOTE_ARGS=${BENCH_VOTE_ARGS:-}                      # extra bench_vote_render.py flags, e.g. --profile --levels 2
SYNTH_DOWNSCALE=${SYNTH_DOWNSCALE:-1}
FOX=${FOX:-.gpu/fox}
PY=${PY:-python3}
EXTRA_TRAIN_ARGS=${EXTRA_TRAIN_ARGS:-}
VOTESPLAT_TRAIN_ARGS=${VOTESPLAT_TRAIN_ARGS:-}                # votesplat's runs only, e.g. --pipeline.model.vote-every-n-steps 1
QUALITY_SCENES=${QUALITY_SCENES:-"votesplat_ns/data/demo build/scenes/nested build/scenes/forward"}
ABLATION_SCENE=${ABLATION_SCENE:-build/scenes/forward}
ABLATION_SEEDS=${ABLATION_SEEDS:-"0 1 2"}                  # one run per variant and seed, all in parallel
QUALITY_STEPS=${QUALITY_STEPS:-3000}
QUALITY_VOTE_START=${QUALITY_VOTE_START:-500}
QUALITY_MASKS=${QUALITY_MASKS:-"gt noisy"}
SWEEP_SCENES=${SWEEP_SCENES:-}
SWEEP_ARGS=${SWEEP_ARGS:-}
QUALITY_ARGS=${QUALITY_ARGS:-}                            # extra benchmarks/quality.py flags, e.g. --vote-every 4
SITE=${SITE:-/tmp/site}                                  # carried wheels are installed here
RUNS=${RUNS:-/tmp/votesplat_runs}  # set it (and OUT) apart to run two run.sh side by side
OUT=${OUT:-/tmp/votesplat_gpu_out}
mkdir -p "$OUT" "$RUNS"

export PYTHONPATH="$PWD:$SITE${PYTHONPATH:+:$PYTHONPATH}"   # working tree first: it wins over the carried wheel
export PATH="$SITE/bin:$PATH"
export PYTHONUNBUFFERED=1 MPLBACKEND=Agg
# the machine's torch environment is read-only and holds no byte-code, so every new process (each rank, each
# worker) would compile torch's and transformers' sources again (10-20 s of a retrofit's set-up, measured); a
# user's pip install has its byte-code: write it once under a prefix the machine lets us write
export PYTHONPYCACHEPREFIX=${PYTHONPYCACHEPREFIX:-/tmp/pycache} PYTHONDONTWRITEBYTECODE=
export TORCH_EXTENSIONS_DIR=/tmp/torch_extensions           # gsplat's JIT build lands in $TORCH_EXTENSIONS_DIR/gsplat_cuda
export MAX_JOBS=${MAX_JOBS:-$(nproc)}
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}    # H100/H200; part of the build's flags, so keep it fixed
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1   # as KINDS.md asks
GSPLAT_BUILD_DIR=$TORCH_EXTENSIONS_DIR/gsplat_cuda
export GSPLAT_PREBUILT_SO=$GSPLAT_BUILD_DIR/gsplat_cuda.so   # read by scripts/gpu/gsplat_prebuilt_csrc.py
CARRIED_BUILD=.gpu/gsplat_build.tar.gz

log() { printf '[run.sh %4ds] %s\n' "$SECONDS" "$*"; }
seconds_left() { echo $((CALL_BUDGET_S - SECONDS)); }
# a limit for `timeout`: the seconds left, but at least $1 (default 10) so a late step still starts
limit_s() { local left; left=$(seconds_left); [ "$left" -gt "${1:-10}" ] && echo "$left" || echo "${1:-10}"; }

# ns-train / ns-eval in-process, with two additions that are the same for both methods:
# LPIPS never downloads AlexNet (the machine has no internet; it is NaN unless the weights are
# in torch's hub cache), and peak torch GPU memory + wall time go to $VOTESPLAT_RUN_STATS.
write_launcher() {
  cat >/tmp/ns_launch.py.$$ <<'PY'
import atexit, json, os, sys, time

start = time.time()


def _write_stats():
    path = os.environ.get("VOTESPLAT_RUN_STATS")
    if not path:
        return
    stats = {"wall_s": round(time.time() - start, 2)}
    torch = sys.modules.get("torch")
    if torch is not None and torch.cuda.is_available() and torch.cuda.is_initialized():
        stats["torch_max_allocated_mib"] = round(torch.cuda.max_memory_allocated() / 2**20, 1)
        stats["torch_max_reserved_mib"] = round(torch.cuda.max_memory_reserved() / 2**20, 1)
    tmp = path + ".tmp"
    with open(tmp, "w") as handle:
        json.dump(stats, handle)
    os.replace(tmp, path)


atexit.register(_write_stats)
command = sys.argv[1]
sys.argv = [f"ns-{command}"] + sys.argv[2:]
from votesplat_ns.ns.patches import splatfacto_metrics_at_first_use

if os.environ.get("VOTESPLAT_STEP_TIMES") and command == "train":  # every step's wall (and phases), no profiler
    from benchmarks.step_times import install_step_times

    phases = os.environ["VOTESPLAT_STEP_TIMES"] != "walls"
    install_step_times(os.environ.get("VOTESPLAT_STEP_TIMES_OUT", "step_times.json"), phases)

if command == "train":
    from nerfstudio.scripts.train import entrypoint
elif command == "eval":
    from nerfstudio.scripts.eval import entrypoint
else:
    sys.exit(f"ns_launch.py: unknown command {command!r} (train or eval)")
# both methods build their PSNR and LPIPS at first use (LPIPS from a local AlexNet or none: no download offline)
with splatfacto_metrics_at_first_use():
    entrypoint()
PY
  mv /tmp/ns_launch.py.$$ /tmp/ns_launch.py  # its own temporary: run.sh may run several times at once
}

# ------------------------------------------------------------------------------------ setup
wheelhouse_stamp() { find .whl -maxdepth 1 -type f -name '*.whl' -printf '%s %f\n' 2>/dev/null | sort | sha256sum | cut -c1-16; }

stage_setup() {
  setup_body 2>&1 | tee -a "$OUT/setup.log"
  return "${PIPESTATUS[0]}"
}

setup_body() {
  log "setup: python $($PY -c 'import sys; print(sys.version.split()[0], sys.executable)')"
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || log "nvidia-smi failed"
  nvcc --version | tail -1 || log "nvcc not found: gsplat cannot JIT-build"
  if ! ls .whl/*.whl >/dev/null 2>&1; then
    log "ERROR: no wheels in .whl/; run scripts/gpu/build_wheelhouse.sh here and carry .whl"
    return 1
  fi
  local stamp; stamp=$(wheelhouse_stamp)
  if [ "$(cat "$SITE/.wheelhouse-stamp" 2>/dev/null)" != "$stamp" ]; then
    log "installing $(find .whl -maxdepth 1 -type f -name '*.whl' | wc -l) wheels into $SITE"
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" .whl/*.whl || return 1
    # The carried votesplat_ns wheel is there for its entry points (dist-info) only: the code
    # comes from the working tree, so no stale copy may shadow it.
    rm -rf "$SITE/votesplat_ns"
    echo "$stamp" >"$SITE/.wheelhouse-stamp"
  else
    log "wheels already installed in $SITE"
  fi
  # Sources older than a carried build let ninja reuse it instead of rebuilding (~200 s).
  find "$SITE/gsplat" -exec touch -h -d 2020-01-01 {} +
  write_launcher

  log "module probe (MISSING ones need a wheel: FALLBACKS=1 scripts/gpu/build_wheelhouse.sh, or add it there)"
  local probe_rc=0
  "$PY" - <<'PY' || probe_rc=1
import importlib, importlib.metadata as md
# ns-train's measured import closure for splatfacto, plus hdbscan's and our plugin's
mods = ["torch", "numpy", "scipy", "sklearn", "joblib", "PIL", "rich", "yaml", "matplotlib", "imageio", "cv2",
        "jaxtyping", "torchmetrics", "tensorboard", "tqdm", "requests", "packaging", "typing_extensions",
        "nerfstudio", "gsplat", "nerfacc", "viser", "tyro", "typeguard", "hdbscan", "plyfile", "fpsample", "rawpy",
        "splines", "pyquaternion", "pytorch_msssim", "tensorly", "pathos", "websockets", "msgspec", "votesplat_ns"]
missing = []
for name in mods:
    try:
        module = importlib.import_module(name)
        print(f"  {name:16s} {getattr(module, '__version__', '')} {getattr(module, '__file__', '')}")
    except Exception as error:
        missing.append(name)
        print(f"  {name:16s} MISSING ({type(error).__name__}: {error})")
import torch
print("torch", torch.__version__, "cuda", torch.version.cuda, "gpu", torch.cuda.get_device_name(0) if torch.cuda.is_available() else None)
from nerfstudio.plugins.registry import discover_methods
methods = discover_methods()[0]
print("ns-train methods include votesplat:", "votesplat" in methods, "| splatfacto:", "splatfacto" in methods)
print("missing modules:", " ".join(missing) if missing else "none")
if missing or "votesplat" not in methods:
    raise SystemExit("setup incomplete: a module is missing or votesplat is not registered (see above)")
PY

  local had_build=0 so_before=""
  if [ -f "$GSPLAT_BUILD_DIR/gsplat_cuda.so" ]; then
    had_build=1
  elif [ -f "$CARRIED_BUILD" ]; then
    log "restoring gsplat build from $CARRIED_BUILD"
    mkdir -p "$TORCH_EXTENSIONS_DIR" && tar -xzf "$CARRIED_BUILD" -C "$TORCH_EXTENSIONS_DIR" && had_build=1
  fi
  [ -f "$GSPLAT_BUILD_DIR/gsplat_cuda.so" ] && so_before=$(stat -c %Y "$GSPLAT_BUILD_DIR/gsplat_cuda.so")
  if [ "$had_build" = 1 ]; then
    # ninja's reuse of a restored build is not reliable (it rebuilt in one try); gsplat first
    # tries `from gsplat import csrc`, so a tiny module that loads the built .so skips the JIT.
    cp scripts/gpu/gsplat_prebuilt_csrc.py "$SITE/gsplat/csrc.py"
    log "gsplat will load the prebuilt $GSPLAT_BUILD_DIR/gsplat_cuda.so"
  fi
  if ! "$PY" -c 'import open3d' 2>/dev/null; then
    # nerfstudio reads a dataset's sparse_pc.ply with open3d (too large to carry): a plyfile shim
    mkdir -p "$SITE/open3d" && cp scripts/gpu/open3d_ply_shim.py "$SITE/open3d/__init__.py"
    log "open3d absent: installed the read_point_cloud shim (scripts/gpu/open3d_ply_shim.py)"
  fi
  log "loading gsplat's CUDA code (JIT build if needed, MAX_JOBS=$MAX_JOBS, arch $TORCH_CUDA_ARCH_LIST)"
  "$PY" - <<'PY' || return 1
import time, torch
t = time.time()
from gsplat.cuda._backend import _C
from gsplat import rasterization
if _C is None:
    raise SystemExit("gsplat's CUDA extension did not load (see the build output above)")
print(f"gsplat CUDA extension ready in {time.time() - t:.1f} s")
device = torch.device("cuda")
n = 64
means = torch.randn(n, 3, device=device) * 0.3 + torch.tensor([0.0, 0.0, 3.0], device=device)
quats = torch.randn(n, 4, device=device)
scales = torch.full((n, 3), 0.05, device=device)
opacities = torch.full((n,), 0.8, device=device)
colors = torch.rand(n, 3, device=device)
K = torch.tensor([[[40.0, 0, 32], [0, 40.0, 24], [0, 0, 1]]], device=device)
image, alpha, _ = rasterization(means, quats, scales, opacities, colors, torch.eye(4, device=device)[None], K, 64, 48)
torch.cuda.synchronize()
print("tiny rasterization ok:", tuple(image.shape), "mean alpha", round(float(alpha.mean()), 4))
PY
  local so_after; so_after=$(stat -c %Y "$GSPLAT_BUILD_DIR/gsplat_cuda.so" 2>/dev/null || true)
  if [ "$had_build" = 0 ] || [ "$so_before" != "$so_after" ]; then
    tar -czf "$OUT/gsplat_build.tar.gz" -C "$TORCH_EXTENSIONS_DIR" gsplat_cuda
    log "fresh gsplat build saved: \$OUT/gsplat_build.tar.gz ($(du -h "$OUT/gsplat_build.tar.gz" | cut -f1)); copy it to $CARRIED_BUILD to skip the build next time"
  else
    log "reused the carried gsplat build"
  fi
  if [ "$probe_rc" != 0 ]; then
    log "setup FAILED: see the module probe above"
    return 1
  fi
  touch "$SITE/.setup-done"
  log "setup done"
}

ensure_setup() {
  if [ -f "$SITE/.setup-done" ] && [ "$(cat "$SITE/.wheelhouse-stamp" 2>/dev/null)" = "$(wheelhouse_stamp)" ]; then
    write_launcher
    return 0
  fi
  stage_setup
}

# ------------------------------------------------------------------------------------ tests
stage_tests() {
  ensure_setup || return 1
  local files=() f
  for f in $GPU_TESTS; do
    if [ -e "$f" ]; then files+=("$f"); else log "skipping $f: not in this tree" | tee -a "$OUT/tests.log"; fi
  done
  [ "${#files[@]}" -gt 0 ] || { log "no test files to run" | tee -a "$OUT/tests.log"; return 1; }
  log "pytest ${files[*]}" | tee -a "$OUT/tests.log"
  timeout "$(limit_s)" "$PY" -m pytest -q -rs -p no:cacheprovider "${files[@]}" 2>&1 | tee -a "$OUT/tests.log"
  return "${PIPESTATUS[0]}"
}

# ------------------------------------------------------------------------------- bench-vote
stage_bench_vote() {
  ensure_setup || return 1
  local rc=0 config dims
  for config in "500000 1440 1080" "100000 720 540"; do
    read -r -a dims <<<"$config"
    set -- "${dims[@]}"
    log "bench_vote_render --num-gaussians $1 --width $2 --height $3" | tee -a "$OUT/bench_vote.log"
    # shellcheck disable=SC2086
    timeout "$(limit_s)" "$PY" benchmarks/bench_vote_render.py --num-gaussians "$1" --width "$2" --height "$3" \
      --backends $BENCH_VOTE_BACKENDS --kernel-configs $KERNEL_CONFIGS $BENCH_VOTE_ARGS 2>&1 | tee -a "$OUT/bench_vote.log"
    [ "${PIPESTATUS[0]}" = 0 ] || rc=1
  done
  return "$rc"
}

# ---------------------------------------------------------------------------------- quality
stage_quality() {
  ensure_setup || return 1
  local work=$RUNS/quality pids=() scene name masks variant rc=0
  rm -rf "$work"; mkdir -p "$work"
  for scene in $QUALITY_SCENES; do
    [ -f "$scene/transforms.json" ] || { log "quality: $scene/transforms.json missing (carry build/scenes)" | tee -a "$OUT/quality.log"; rc=1; continue; }
    name=$(basename "$scene")
    for masks in $QUALITY_MASKS; do
      # shellcheck disable=SC2086
      timeout "$(limit_s)" "$PY" benchmarks/quality.py --scenes "$scene" --masks "$masks" --steps "$QUALITY_STEPS" \
        --vote-start "$QUALITY_VOTE_START" --work-dir "$work/$name-$masks" $QUALITY_ARGS >"$work/$name-$masks.log" 2>&1 &
      pids+=($!)
    done
  done
  if [ -f "$ABLATION_SCENE/transforms.json" ]; then
    local seed run
    for seed in $ABLATION_SEEDS; do
      for variant in "full" "no distortion" "2D blending" "alpha*T weights"; do
        run="ablation-${variant//[^a-zA-Z0-9]/_}-seed$seed"
        # shellcheck disable=SC2086
        timeout "$(limit_s)" "$PY" benchmarks/quality.py --scenes "$ABLATION_SCENE" --ablation --variants "$variant" \
          --seeds "$seed" --steps "$QUALITY_STEPS" --vote-start "$QUALITY_VOTE_START" $QUALITY_ARGS \
          --work-dir "$work/$run" >"$work/$run.log" 2>&1 &
        pids+=($!)
      done
    done
  fi
  log "quality: ${#pids[@]} runs started, $QUALITY_STEPS steps each" | tee -a "$OUT/quality.log"
  for pid in "${pids[@]}"; do wait "$pid" || rc=1; done
  log "quality: all runs ended (exit $rc)" | tee -a "$OUT/quality.log"
  { for f in "$work"/*/quality.md "$work"/*/ablation.md; do [ -f "$f" ] && { echo "## $f"; cat "$f"; echo; }; done; } >"$OUT/quality.md"
  if compgen -G "$work/ablation-*/ablation.json" >/dev/null; then
    { echo "## ablation: mean ± std over seeds $ABLATION_SEEDS"; "$PY" benchmarks/quality.py --summarize "$work"/ablation-*/ablation.json; } >>"$OUT/quality.md" 2>&1
  fi
  cat "$OUT/quality.md" | tee -a "$OUT/quality.log"
  tail -n 5 "$work"/*.log >>"$OUT/quality.log"
  # metrics, comparison pictures and logs (no checkpoints) come back
  (cd "$work" && find . \( -name 'metrics.json' -o -name '*.png' -o -name '*.md' -o -name '*.log' -o -name 'quality.json' -o -name 'ablation.json' \) \
     -not -path '*/noisy_masks/*' -print0 | tar --null -czf "$OUT/quality.tar.gz" -T -)
  return "$rc"
}

# benchmarks/sweep.py on $SWEEP_SCENES (carried folders of votesplat synth scenes) with $SWEEP_ARGS
# (training/clustering variants, masks, steps, --jobs); sweep.md / sweep.json come back, rewritten
# after every finished run, so a call cut short still reports what finished.
stage_sweep() {
  ensure_setup || return 1
  # SWEEP_TAG names the work folder and the returned files, so two sweeps can run side by side
  # (run setup first, then e.g. `SWEEP_TAG=a ... run.sh sweep & SWEEP_TAG=b ... run.sh sweep & wait`)
  local tag=${SWEEP_TAG:+_$SWEEP_TAG}
  local work=$RUNS/sweep$tag
  rm -rf "$work"; mkdir -p "$work"
  # shellcheck disable=SC2086
  timeout "$(limit_s)" "$PY" benchmarks/sweep.py ${SWEEP_SCENES:+--scenes $SWEEP_SCENES} --work-dir "$work" $SWEEP_ARGS >"$OUT/sweep$tag.log" 2>&1
  local rc=$?
  cp "$work/sweep.md" "$OUT/sweep$tag.md" 2>/dev/null && cp "$work/sweep.json" "$OUT/sweep$tag.json" || log "sweep$tag: no run finished (see sweep$tag.log)"
  grep -h -i -E "error|Traceback" "$work"/*/*/worker.log 2>/dev/null | sort | uniq -c | head -20 >>"$OUT/sweep$tag.log"
  return "$rc"
}


# ----------------------------------------------------------------------------------- training
# train_one EXPERIMENT METHOD DATA DOWNSCALE LOG [votesplat args...]: trains, evaluates and
# writes $RUNS/result_<experiment>_<method>.json.
train_one() {
  local experiment=$1 method=$2 data=$3 downscale=$4 log_file=$5
  shift 5
  local run_dir=$RUNS/$experiment/$method/run
  local result=$RUNS/result_${experiment}_${method}.json
  local stats=$RUNS/stats_${experiment}_${method}.json eval_json=$RUNS/eval_${experiment}_${method}.json
  local gpu_log=$RUNS/gpu_${experiment}_${method}.csv
  rm -rf "$run_dir" "$result" "$stats" "$eval_json" "$gpu_log" "$gpu_log.meta"
  local reserve=$EVAL_RESERVE_S
  [ "${EVAL:-1}" = 1 ] || reserve=5  # without ns-eval, the training takes what would be kept for it
  local train_limit=$(( $(seconds_left) - reserve ))
  local status=ok eval_status="not run" rc=0 wall=0
  if [ "$train_limit" -lt 30 ]; then
    status="skipped: $(seconds_left) s left of CALL_BUDGET_S=$CALL_BUDGET_S"
    log "$experiment/$method $status" | tee -a "$log_file"
  else
    local baseline_mib
    baseline_mib=$(nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits | head -1)
    nvidia-smi --query-gpu=memory.used,utilization.gpu --format=csv,noheader,nounits -lms 500 >"$gpu_log" 2>/dev/null &
    local logger_pid=$!
    log "ns-train $method on $data: $STEPS steps, time limit ${train_limit} s" | tee -a "$log_file"
    local t0; t0=$(date +%s.%N)
    # shellcheck disable=SC2086
    VOTESPLAT_RUN_STATS=$stats VOTESPLAT_STEP_TIMES_OUT=$OUT/steps_${experiment}_${method}.json timeout --signal=INT --kill-after=20 "$train_limit" \
      "$PY" /tmp/ns_launch.py train "$method" --data "$data" --max-num-iterations "$STEPS" \
      --vis tensorboard --viewer.quit-on-train-completion True \
      --output-dir "$RUNS" --experiment-name "$experiment" --timestamp run \
      "$@" $EXTRA_TRAIN_ARGS nerfstudio-data --downscale-factor "$downscale" >>"$log_file" 2>&1
    rc=$?
    wall=$(awk -v a="$(date +%s.%N)" -v b="$t0" 'BEGIN { printf "%.1f", a - b }')
    kill "$logger_pid" 2>/dev/null; wait "$logger_pid" 2>/dev/null
    echo "$baseline_mib" >"$gpu_log.meta"
    if [ "$rc" = 124 ] || [ "$rc" = 137 ]; then status="timeout after ${train_limit} s"; elif [ "$rc" != 0 ]; then status="failed (exit $rc)"; fi
    log "$experiment/$method: $status, ${wall} s wall" | tee -a "$log_file"
    if [ "${EVAL:-1}" = 1 ] && [ -f "$run_dir/config.yml" ] && ls "$run_dir"/nerfstudio_models/*.ckpt >/dev/null 2>&1; then
      log "ns-eval $experiment/$method" | tee -a "$log_file"
      timeout "$(limit_s 20)" \
        "$PY" /tmp/ns_launch.py eval --load-config "$run_dir/config.yml" --output-path "$eval_json" >>"$log_file" 2>&1
      rc=$?
      case "$rc" in 0) eval_status=ok ;; 124|137) eval_status="timeout" ;; *) eval_status="failed (exit $rc)" ;; esac
      log "ns-eval $experiment/$method: $eval_status" | tee -a "$log_file"
    fi
  fi
  "$PY" - "$result" "$experiment" "$method" "$data" "$STEPS" "$status" "$wall" "$run_dir" "$stats" "$eval_json" "$gpu_log" "$eval_status" <<'PY'
import glob, json, os, re, sys
result, experiment, method, data, steps, status, wall, run_dir, stats, eval_json, gpu_log, eval_status = sys.argv[1:]
entry = {"method": method, "data": data, "steps": int(steps), "status": status, "eval_status": eval_status,
         "wall_s": round(float(wall or 0), 1)}
try:
    import subprocess
    entry["gpu"] = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                                  capture_output=True, text=True, timeout=20).stdout.strip().splitlines()[0]
except Exception:
    entry["gpu"] = None
if os.path.exists(stats):
    entry["process"] = json.load(open(stats))
if os.path.exists(gpu_log):
    rows = [line.split(",") for line in open(gpu_log) if re.match(r"^\s*\d", line)]
    if rows:
        used = [float(r[0]) for r in rows]
        util = [float(r[1]) for r in rows]
        baseline = None
        if os.path.exists(gpu_log + ".meta"):
            baseline = float(open(gpu_log + ".meta").read().strip() or "nan")
        entry["gpu_peak_memory_used_mib"] = max(used)
        entry["gpu_baseline_memory_used_mib"] = baseline
        entry["gpu_util_mean_pct"] = round(sum(util) / len(util), 1)
checkpoints = sorted(glob.glob(os.path.join(run_dir, "nerfstudio_models", "step-*.ckpt")))
if checkpoints:
    import torch
    state = torch.load(checkpoints[-1], map_location="cpu", weights_only=False)
    means = [v for k, v in state["pipeline"].items() if k.endswith("gauss_params.means")]
    entry["checkpoint_step"] = int(state.get("step", -1))
    entry["num_gaussians"] = int(means[0].shape[0]) if means else None
if os.path.exists(eval_json):
    entry["eval"] = json.load(open(eval_json)).get("results")
tmp = result + ".tmp"
json.dump(entry, open(tmp, "w"), indent=2)
os.replace(tmp, result)
PY
}

# summarize OUT_JSON RESULT_JSON...: the methods' results in one JSON ({"gpu": [...], "methods": {method: result}}),
# what benchmarks/step_times.py --table and benchmarks/psnr_seeds.py read.
summarize() {
  "$PY" - "$@" <<'PY'
import json, os, sys
out, inputs = sys.argv[1], sys.argv[2:]
methods = {}
for path in inputs:
    data = json.load(open(path))
    methods[data["method"]] = data
summary = {"gpu": sorted({m.get("gpu") for m in methods.values() if m.get("gpu")}), "methods": methods}
text = json.dumps(summary, indent=2)
with open(out + ".tmp", "w") as handle:
    handle.write(text + "\n")
os.replace(out + ".tmp", out)
print(text)
PY
}

set_vote_args() {  # EXPERIMENT DATA -> VOTE_ARGS, votesplat's extra flags
  local levels
  if [ "$1" = fox ]; then
    levels=("${FOX_MASK_LEVELS[@]}")
    VOTE_ARGS=("$VOTE_MASK_SOURCE_FLAG" folder "$VOTE_MASK_FOLDER_FLAG" "$2/votesplat_masks")
  else
    levels=("${SYNTH_MASK_LEVELS[@]}")
    VOTE_ARGS=("$VOTE_MASK_SOURCE_FLAG" dataset)
  fi
  VOTE_ARGS+=("$VOTE_MASK_LEVELS_FLAG" "${levels[@]}" "$MODEL_VOTE_LEVELS_FLAG" "${levels[@]}"
              "$VOTE_CACHE_DIR_FLAG" "$RUNS/votesplat_cache_$1")
}

train_compare() {  # EXPERIMENT DATA DOWNSCALE
  local experiment=$1 data=$2 downscale=$3
  local log_file=$OUT/train_${experiment}.log results=() method
  ensure_setup || return 1
  if [ ! -f "$data/transforms.json" ]; then
    log "ERROR: $data/transforms.json not found (carry .gpu; for the fox run scripts/gpu/prepare_fox.py here first)" | tee -a "$log_file"
    return 1
  fi
  for method in $METHODS; do
    case "$method" in
      splatfacto) train_one "$experiment" splatfacto "$data" "$downscale" "$log_file" ;;
      votesplat) set_vote_args "$experiment" "$data"
                 # a fresh vote cache each run: its one-time build is part of votesplat's wall time
                 rm -rf "$RUNS/votesplat_cache_$experiment"
                 # shellcheck disable=SC2086
                 train_one "$experiment" votesplat "$data" "$downscale" "$log_file" "${VOTE_ARGS[@]}" $VOTESPLAT_TRAIN_ARGS ;;
      *) log "unknown method $method (splatfacto or votesplat)" | tee -a "$log_file"; return 1 ;;
    esac
    results+=("$RUNS/result_${experiment}_${method}.json")
  done
  summarize "$OUT/train_${experiment}.json" "${results[@]}" || return 1
  # a method that did not train or evaluate makes the stage fail
  ! grep -L -E '"status": "ok"' "${results[@]}" | grep -q . && ! grep -l -E '"eval_status": "(failed|timeout)' "${results[@]}" | grep -q .
}

# votesplat's vote_start_step: from its flags when they set one, else the default 500
vote_start_step() {
  if [[ "$VOTESPLAT_TRAIN_ARGS $EXTRA_TRAIN_ARGS" =~ --pipeline\.model\.vote-start-step[=\ ]+([0-9]+) ]]; then
    echo "${BASH_REMATCH[1]}"
  else
    echo 500
  fi
}

# A throwaway splatfacto training of $WARM_UP_STEPS (50) steps into FOLDER/warm_up: the first training of a machine
# takes ~4 s more at step 0, whichever method it is; its files stay there, it is not a measurement.
warm_up_run() {  # FOLDER EXPERIMENT [DATA]
  local steps=${WARM_UP_STEPS:-50}
  [ "$steps" -gt 0 ] || return 0
  log "warm-up run, splatfacto, $steps steps"
  OUT=$1/warm_up RUNS=$1/warm_up/runs STEPS=$steps EVAL=0 METHODS=splatfacto VOTESPLAT_STEP_TIMES= \
    CALL_BUDGET_S=$(limit_s 60) bash "$0" "train-$2" ${3:-} >"$1/warm_up.log" 2>&1 \
    || log "the warm-up run failed ($1/warm_up.log); going on"
}

# ---------------------------------------------------------------------------- train-balanced
stage_train_balanced() {  # EXPERIMENT [DATA]
  local experiment=$1 data=${2:-} base method dir index=0 left runs_left
  local order=(${ORDER:-splatfacto votesplat votesplat splatfacto}) folders=() vote_start
  vote_start=$(vote_start_step)  # the table's split of the steps
  case "$experiment" in
    fox) [ -z "$data" ] || { log "train-balanced: fox takes no DATA (it trains \$FOX, $FOX)"; return 1; } ;;
    synthetic) ;;
    *) log "train-balanced: fox or synthetic, not '$experiment'"; return 1 ;;
  esac
  ensure_setup || return 1
  base=$RUNS/balanced_$experiment
  rm -rf "$base" && mkdir -p "$base"
  warm_up_run "$base" "$experiment" $data
  for method in "${order[@]}"; do
    index=$((index + 1))
    dir=$base/$index-$method
    runs_left=$((${#order[@]} - index + 1))
    left=$(seconds_left)
    log "train-balanced: run $index of ${#order[@]}, $method, $((left / runs_left)) s"
    OUT=$dir RUNS=$dir/runs TRITON_CACHE_DIR=$dir/triton METHODS=$method VOTESPLAT_STEP_TIMES=${BALANCED_STEP_TIMES:-walls} \
      CALL_BUDGET_S=$((left / runs_left)) bash "$0" "train-$experiment" $data >"$dir.log" 2>&1 \
      || log "train-balanced: run $index ($method) did not finish ($dir.log)"
    rm -rf "$dir/runs" "$dir/triton"
    folders+=("$dir")
    tar czf "$OUT/balanced_$experiment.tar.gz" -C "$base" --exclude='warm_up*' . || return 1
    "$PY" benchmarks/step_times.py --table "${folders[@]}" --vote-start "$vote_start" >"$OUT/balanced_$experiment.md" || return 1
  done
  cat "$OUT/balanced_$experiment.md"
}

# ------------------------------------------------------------------------------------- main
[ "$#" -gt 0 ] || { sed -n '2,/^set -uo/p' "$0" | sed '$d'; exit 2; }
rc=0
while [ "$#" -gt 0 ]; do
  stage=$1; shift
  log "== $stage" >&2
  case "$stage" in
    setup) stage_setup || rc=1 ;;
    tests) stage_tests || rc=1 ;;
    bench-vote) stage_bench_vote || rc=1 ;;
    quality) stage_quality || rc=1 ;;
    sweep) stage_sweep || rc=1 ;;
    train-fox) train_compare fox "$FOX" 2 || rc=1 ;;
    train-synthetic)
      data=.gpu/synthetic
      if [ "$#" -gt 0 ] && [ -d "$1" ]; then data=$1; shift; fi
      train_compare synthetic "$data" "$SYNTH_DOWNSCALE" || rc=1 ;;
    train-balanced)
      [ "$#" -gt 0 ] || { log "train-balanced: fox or synthetic [DATA]" >&2; rc=2; continue; }
      experiment=$1; shift; data=
      if [ "$#" -gt 0 ] && [ -d "$1" ]; then data=$1; shift; fi
      stage_train_balanced "$experiment" "$data" || rc=1 ;;
    *) log "unknown stage '$stage' (setup, tests, bench-vote, quality, sweep, train-fox, train-synthetic [DATA], train-balanced fox|synthetic [DATA])" >&2; rc=2 ;;
  esac
done
log "done (exit $rc)" >&2
exit "$rc"
