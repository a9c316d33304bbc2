# Installed as gsplat/csrc.py by scripts/gpu/run.sh when a prebuilt gsplat_cuda.so is carried.
# Loads a prebuilt gsplat_cuda.so (built on the same image) so gsplat skips its JIT build.
import importlib.util
import os

import torch  # noqa: F401  (libtorch symbols first)

_spec = importlib.util.spec_from_file_location("gsplat_cuda", os.environ["GSPLAT_PREBUILT_SO"])
_module = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_module)
globals().update({k: v for k, v in vars(_module).items() if not k.startswith("__")})
