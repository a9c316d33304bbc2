#!/usr/bin/env bash
# Fills .whl/ with every wheel the lent GPU machine needs to run ns-train splatfacto / votesplat.
#
# That machine has Python 3.12 (x86_64), torch 2.11+cu130, numpy 2.5 and a large image of
# packages (device KINDS.md, "Python packages already there": scipy, scikit-learn, joblib,
# pillow, rich, pyyaml, imageio, jaxtyping, torchmetrics, matplotlib, opencv-python-headless,
# tensorboard, ninja, ...) but no internet. We carry only what that list lacks: nerfstudio's
# start-up path for splatfacto (measured: 21 wheels), our plugin's run-time imports and our
# own wheel (its dist-info holds the nerfstudio.method_configs entry point that makes
# `ns-train votesplat` discoverable). nerfstudio's heavy optional imports (open3d, mediapy,
# wandb, comet_ml, pymeshlab, xatlas, trimesh) are lazy on the ns-train/ns-eval splatfacto
# path and are NOT carried.
#
# Usage (here, in the repo root or anywhere):
#   bash scripts/gpu/build_wheelhouse.sh             # the normal set (24 wheels, ~29 MB)
#   SEMANTICS=1 bash scripts/gpu/build_wheelhouse.sh # + open_clip/segment-anything (+2.4 MB),
#                                                    #   only for code paths that import them
#   FALLBACKS=1 bash scripts/gpu/build_wheelhouse.sh # + small copies of packages the image
#                                                    #   should have (if `run.sh setup` reports
#                                                    #   one MISSING)
# Exactly one version of each distribution ends up in .whl/ (two stop pip's install there);
# the folder is rebuilt in .whl.tmp and swapped in only when complete.
set -euo pipefail
cd "$(dirname "$0")/../.."

WHEELHOUSE=${WHEELHOUSE:-.whl}
if [ -x .venv/bin/python ]; then PYTHON=${PYTHON:-.venv/bin/python}; else PYTHON=${PYTHON:-python3}; fi
FALLBACKS=${FALLBACKS:-0}
SEMANTICS=${SEMANTICS:-0}

# nerfstudio 1.1.5's import closure for ns-train/ns-eval splatfacto, as measured on the GPU
# machine. fpsample 1.0.2 has no cp312 wheel; 0.3.3 has and is API-compatible for nerfstudio.
NERFSTUDIO_PATH=(
  nerfstudio==1.1.5 gsplat==1.4.0 nerfacc==0.5.2 viser==0.2.7 fpsample==0.3.3
  tyro==1.0.17 docstring_parser==0.18.0 typeguard==4.6.0
  websockets==17.4 msgspec==0.22.0
  splines==0.3.0 pyquaternion==0.9.9 pytorch-msssim==1.0.0 tensorly==0.10.0
  pathos==0.3.5 dill==0.4.1 multiprocess==0.70.19 ppft==1.7.8 pox==0.3.7
  appdirs==1.4.4 rawpy==0.28.0
)
# Our plugin's run-time imports beyond the image (hdbscan's scipy/scikit-learn/joblib are
# in the image).
PLUGIN=(plyfile==1.1.5 hdbscan==0.8.44)
# Only with SEMANTICS=1: votesplat_ns imports these lazily (CLIP features, SAM masks), never
# on the training/benchmark path, and no weights for them exist offline.
SEMANTICS_GROUP=(open_clip_torch==2.32.0 ftfy==6.3.1 wcwidth==0.9.4 segment-anything==1.0)
# Only with FALLBACKS=1: small packages KINDS.md lists as present, for the case a probe in
# `run.sh setup` finds one missing. scipy (~35 MB), matplotlib and opencv are too big to carry.
FALLBACK=(
  scikit-learn==1.9.1 joblib==1.6.0 threadpoolctl==3.8.0
  rich==15.0.0 markdown-it-py==4.3.0 mdurl==0.1.2 pygments==2.21.0 pyyaml==6.0.3
  imageio==2.38.1 jaxtyping==0.3.11 wadler-lindig==0.1.8 typing_extensions==4.16.0
  torchmetrics==1.9.0 lightning-utilities==0.15.3
)

PLATFORM_ARGS=(
  --only-binary=:all: --no-deps --python-version 3.12 --implementation cp --abi cp312
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64
  --platform manylinux_2_24_x86_64 --platform manylinux_2_17_x86_64
  --platform manylinux2014_x86_64 --platform manylinux1_x86_64
)

wanted=("${NERFSTUDIO_PATH[@]}" "${PLUGIN[@]}")
if [ "$SEMANTICS" = 1 ]; then wanted+=("${SEMANTICS_GROUP[@]}"); fi
if [ "$FALLBACKS" = 1 ]; then wanted+=("${FALLBACK[@]}"); fi

staging="$WHEELHOUSE.tmp"
rm -rf "$staging"
mkdir -p "$staging"

echo "downloading ${#wanted[@]} wheels for cp312 manylinux x86_64 into $staging"
# One pip call resolves nothing (--no-deps) and fails loudly on a pin with no cp312 wheel.
# --abi also admits pure-python (none/abi3) wheels: pip adds them to the tag list itself.
# (pip's config here may name local indexes that do not exist; their warnings are noise.)
"$PYTHON" -m pip download -q --disable-pip-version-check "${PLATFORM_ARGS[@]}" -d "$staging" "${wanted[@]}" \
  2> >(grep -v "Location 'file:" >&2)

echo "building votesplat_ns's own wheel (entry points for ns-train discovery)"
# Built from a copy so setuptools leaves no build/ or egg-info in the shared working tree.
source_copy=$(mktemp -d)
trap 'rm -rf "$source_copy" "$source_copy.log"' EXIT
cp -r pyproject.toml README.md votesplat_ns "$source_copy"/
find "$source_copy" -name __pycache__ -prune -exec rm -rf {} +
if ! "$PYTHON" -m pip wheel -q --disable-pip-version-check --no-deps --no-build-isolation \
  -w "$PWD/$staging" "$source_copy" >"$source_copy.log" 2>&1; then
  cat "$source_copy.log" >&2
  echo "error: building votesplat_ns's wheel failed (needs setuptools>=64 in $PYTHON)" >&2
  exit 1
fi
rm -f "$source_copy.log"

# Every wheel must be installable on the target: pip refuses a wrong tag when told the
# target's platform ("... is not a supported wheel on this platform").
"$PYTHON" -m pip install --dry-run -q --disable-pip-version-check --no-index "${PLATFORM_ARGS[@]}" \
  --target "$staging/dry-run-target" "$staging"/*.whl 2> >(grep -v "Location 'file:" >&2)
rm -rf "$staging/dry-run-target"

# ... and appear once; and whatever they require must be carried, in the image, or known to
# be imported lazily on our path.
"$PYTHON" - "$staging" <<'PY'
import collections, re, sys, zipfile
from pathlib import Path
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name, parse_wheel_filename

folder = Path(sys.argv[1])
wheels = sorted(folder.glob("*.whl"))
names = collections.Counter(canonicalize_name(parse_wheel_filename(w.name)[0]) for w in wheels)
dupes = [n for n, c in names.items() if c > 1]
if dupes:
    sys.exit(f"error: more than one version of {dupes} in {folder}; pin one version each")

# Device KINDS.md, "Python packages already there" (read off the image on 2026-11-17).
device_has = set(canonicalize_name(n) for n in """
absl-py accelerate aiofiles aiohappyeyeballs aiohttp aiosignal annotated-doc anyio attrs botorch
build certifi charset-normalizer chex click cloudpickle cmake colorama contourpy coverage
cuda-bindings cuda-core cuda-pathfinder cuda-toolkit cupy-cuda13x cycler cython diffrax e3nn
einops equinox etils execnet filelock flatbuffers flax fonttools formulaic frozenlist fsspec
gpytorch grpcio h11 h5py hf-xet httpcore httpx huggingface-hub humanize hypothesis idna imageio
iniconfig interface-meta jax jax-cuda13-pjrt jax-cuda13-plugin jaxlib jaxtyping jinja2 joblib
kiwisolver lazy-loader lightning lightning-utilities linear-operator lineax llvmlite lxml
markdown markdown-it-py markupsafe matplotlib mdurl meson ml-dtypes mpi4py mpmath msgpack
multidict multipledispatch mypy-extensions nanobind narwhals networkx ninja numba numba-cuda
numpy numpyro nvidia-cublas nvidia-cuda-cupti nvidia-cuda-nvrtc nvidia-cuda-runtime
nvidia-cudnn-cu13 nvidia-cufft nvidia-cufile nvidia-curand nvidia-cusolver nvidia-cusparse
nvidia-cusparselt-cu13 nvidia-ml-py nvidia-nccl-cu13 nvidia-nvjitlink nvidia-nvshmem-cu13
nvidia-nvtx onnx onnx-ir onnxruntime onnxscript opencv-python-headless optax opt-einsum
opt-einsum-fx optimistix orbax-checkpoint packaging pandas pathspec patsy peft pillow pip pluggy
portalocker prometheus-client propcache protobuf psutil pyarrow pybind11 py-cpuinfo pygments
pyparsing pyproject-hooks pyre-extensions pytest pytest-benchmark pytest-cov pytest-mock
pytest-timeout pytest-xdist python-dateutil pytorch-lightning pyyaml regex requests rich
sacrebleu safetensors scikit-build-core scikit-image scikit-learn scipy seaborn sentencepiece
sentence-transformers setuptools shellingham simplejson six sortedcontainers statsmodels sympy
tabulate tensorboard tensorboard-data-server tensorstore threadpoolctl tifffile tiktoken timm
tokenizers toolz torch torchaudio torchdiffeq torch-geometric torchmetrics torchvision tqdm
transformers treescope triton typer typing-extensions typing-inspect urllib3 uvloop
wadler-lindig werkzeug wheel wrapt xarray xxhash yarl zipp
""".split())
# Declared but not imported by ns-train/ns-eval splatfacto or votesplat (measured with
# nerfstudio 1.1.5: imported lazily, by other methods, or only by ns-process-data/ns-export).
lazy_ok = set(canonicalize_name(n) for n in """
open3d mediapy wandb comet-ml pymeshlab xatlas trimesh av awscli gdown ipywidgets jupyterlab
nuscenes-devkit pytest pre-commit pyright ruff sshconf tensorboardx pycolmap newrawpy
projectaria-tools importlib-metadata torch-fidelity opencv-python timm ipython cryptography
plotly pyngrok python-socketio yourdfpy nodeenv pyliblzfse msgpack-numpy xxhash
open-clip-torch segment-anything
""".split())
env = {"python_version": "3.12", "python_full_version": "3.12.3", "sys_platform": "linux",
       "platform_system": "Linux", "platform_machine": "x86_64", "implementation_name": "cpython",
       "platform_python_implementation": "CPython", "os_name": "posix", "extra": ""}
unmet = collections.defaultdict(list)
for w in wheels:
    with zipfile.ZipFile(w) as z:
        meta = next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))
        for line in z.read(meta).decode().splitlines():
            if not line.startswith("Requires-Dist:"):
                continue
            req = Requirement(line.split(":", 1)[1].strip())
            if req.marker is not None and not req.marker.evaluate(env):
                continue
            name = canonicalize_name(req.name)
            if name not in names and name not in device_has and name not in lazy_ok:
                unmet[name].append(w.name.split("-")[0])
total = sum(w.stat().st_size for w in wheels)
print(f"{len(wheels)} wheels, {total / 1e6:.1f} MB")
for name, by in sorted(unmet.items()):
    print(f"note: {name} is required by {sorted(set(by))} and neither carried nor listed on the device")
PY

rm -rf "$WHEELHOUSE"
mv "$staging" "$WHEELHOUSE"
du -sh "$WHEELHOUSE"
