"""Masks from Segment Anything's automatic mask generator, one label image per granularity level.

The checkpoint is never downloaded: :func:`check_sam_checkpoint` names the official file to fetch.
"""

from __future__ import annotations

import copy
import functools
import hashlib
import os
import threading
import time
from contextlib import contextmanager, nullcontext
from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional, Sequence, Tuple

import numpy as np
from PIL import Image

from votesplat_ns.core.image_files import PathLike
from votesplat_ns.core.mask_source_base import MaskSource, validate_levels
from votesplat_ns.core.sam_decoder import DECODER_MODES, DEFAULT_DECODER
from votesplat_ns.errors import VoteSplatInputError, device_problem, load_failure_reason

SAM_CHECKPOINT_FILES = {
    "vit_h": "sam_vit_h_4b8939.pth",
    "vit_l": "sam_vit_l_0b3195.pth",
    "vit_b": "sam_vit_b_01ec64.pth",
}
"""File names of the official SAM checkpoints, as listed in the README of facebookresearch/segment-anything."""


SAM_LEVELS = ("default", "s", "m", "l")


_OUTPUT_INDEX = {"default": None, "s": 0, "m": 1, "l": 2}
"""SAM multimask output index per level; ``None``: all three outputs together (the standard generator)."""


SAM_PRECISIONS = ("fp32", "tf32", "bf16")
"""How SAM's encoder and decoder compute: ``fp32`` as segment_anything runs them (the masks are its masks);
``tf32``: float32 matrix products on TensorFloat-32 tensor cores (``torch.set_float32_matmul_precision("high")``;
on a CPU the same as fp32); ``bf16``: under ``torch.autocast`` in bfloat16. The last two are faster on a GPU and
give masks that differ a little from fp32's."""

SAM_PRECISION_CHOICES = ("auto",) + SAM_PRECISIONS
"""What a user may ask for: ``auto`` is :func:`default_sam_precision` of the device SAM runs on."""


def default_sam_precision(device: Optional[str] = None) -> str:
    """``bf16`` on a CUDA device that computes in bfloat16 (compute capability 8.0 or newer; older GPUs only emulate
    it, slowly), else ``fp32``: vit_h in fp32 takes 1.8-2.0 s per 1080p image on an H200 (its five encoder passes
    alone 1.0 s), in bf16 0.92-1.02 s, and bf16's masks agree with fp32's at mask IoU 0.99 with no filter decision
    changed (BENCHMARKS.md, "SAM masks"); SAM 2's predictor runs in bfloat16 likewise. ``device`` None: cuda when
    available."""
    import torch

    resolved = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    if resolved.type == "cuda" and torch.cuda.get_device_properties(resolved).major >= 8:
        return "bf16"
    return "fp32"


def check_sam_device(device: str) -> None:
    """A one-line :class:`VoteSplatInputError` for a SAM device this machine does not have
    (:func:`votesplat_ns.errors.device_problem`)."""
    problem = device_problem(device)
    if problem is not None:
        raise VoteSplatInputError(
            f"SAM device '{device}': {problem}; give cpu or a device it has to --sam-device (votesplat masks) or "
            "--pipeline.datamanager.sam-device (ns-train), or leave it out (cuda where available, else cpu)"
        )


DEFAULT_POINTS_PER_BATCH = 256
"""Point prompts per decoder call. The decoder's activations take some 20-30 MiB per prompt in fp32 (the image
embedding is repeated per prompt through its two-way transformer and upscaling), whatever the image's size: 5-8 GiB
at 256. Its masks are upscaled apart, :data:`UPSCALE_BUDGET_BYTES` at a time. 1024 (one call per crop of 32 x 32
points) takes 15% off a vit_b image in bf16 at twice the working memory, 2-3% off a vit_h one (BENCHMARKS.md, "SAM
masks")."""

UPSCALE_BUDGET_BYTES = 1 << 31
"""Device memory for the masks upscaled at once: per mask, the 1024 x 1024 step of ``Sam.postprocess_masks`` (4 MiB)
and 8 bytes per crop pixel (the float logits and the thresholded masks), so a 4K crop takes smaller chunks."""


class SamMaskSource(MaskSource):
    """Segment Anything's automatic mask generator, LangSplat-style hierarchical levels.

    Levels (any subset, in any order, of ``("default", "s", "m", "l")``):
      - ``"s"``, ``"m"``, ``"l"``: masks from SAM's multimask output 0, 1, 2 (subpart, part,
        whole), each level filtered on its own so that NMS only compares masks of one
        granularity (LangSplat's modified generator likewise keeps the three apart);
      - ``"default"``: the standard generator's masks, all three outputs together.
    All levels come from one encoder pass per crop and one decoder pass per point batch
    (:class:`SamLevelsMaskGenerator`); each level's labels are those of segment_anything's
    ``SamAutomaticMaskGenerator`` run on that level alone.
    Each level's masks are merged with :func:`labels_from_binary_masks` (smaller mask wins).
    LangSplat additionally removes redundant masks by score/inner-overlap; that step is not done.

    The generator defaults are LangSplat's (points_per_side=32, pred_iou_thresh=0.7,
    box_nms_thresh=0.7, stability_score_thresh=0.85, crop_n_layers=1, min_mask_region_area=100), with
    ``points_per_batch`` prompts per decoder call (:data:`DEFAULT_POINTS_PER_BATCH`). ``precision="bf16"`` runs
    SAM's encoder and decoder in bfloat16, ``"tf32"`` their float32 matrix products on TensorFloat-32
    (:class:`SamSteps`); the masks then differ a little from fp32's. ``"auto"`` (default) is bf16 on a CUDA
    device with bfloat16 and fp32 elsewhere (:func:`default_sam_precision`), decided when the source is made. On a
    GPU the prompt decoder and the masks' stability scores are compiled (``compile_decoder``, :class:`SamSteps`).
    Images whose long side exceeds ``max_long_side`` are downscaled before SAM (masks come back
    at that size; the vote maps are resized to the training resolution later).

    The checkpoint is never downloaded. Tests may pass ``sam_model`` (an already-built ``Sam``).
    Two views may be asked for at once (``overlaps_views``): one model serves both, and the device works on one
    view while the host works on the other (:meth:`SamLevelsMaskGenerator.label_images`).
    """

    overlaps_views = True

    def __init__(
        self,
        checkpoint: Optional[PathLike] = None,
        model_type: str = "vit_h",
        device: Optional[str] = None,
        levels: Sequence[str] = SAM_LEVELS,
        points_per_side: int = 32,
        points_per_batch: int = DEFAULT_POINTS_PER_BATCH,
        pred_iou_thresh: float = 0.7,
        stability_score_thresh: float = 0.85,
        box_nms_thresh: float = 0.7,
        crop_n_layers: int = 1,
        crop_n_points_downscale_factor: int = 1,
        min_mask_region_area: int = 100,
        max_long_side: Optional[int] = 1080,
        precision: str = "auto",
        compile_decoder: bool = True,
        sam_model: Any = None,
    ):
        if model_type not in SAM_CHECKPOINT_FILES:
            raise VoteSplatInputError(
                f"unknown SAM model type '{model_type}'; use one of {sorted(SAM_CHECKPOINT_FILES)}"
            )
        self.levels = validate_levels(levels, "SAM mask source")
        unknown = [level for level in self.levels if level not in SAM_LEVELS]
        if unknown:
            raise VoteSplatInputError(f"unknown SAM mask levels {unknown}; use a subset of {list(SAM_LEVELS)}")
        if precision not in SAM_PRECISION_CHOICES:
            raise VoteSplatInputError(f"unknown SAM precision '{precision}'; use one of {list(SAM_PRECISION_CHOICES)}")
        if device is not None:
            check_sam_device(device)
        if precision == "auto":  # resolved here, so that the cache key names the arithmetic that made the masks
            precision = default_sam_precision(device)
        if int(points_per_batch) < 1:
            raise VoteSplatInputError(
                f"SAM points per batch {points_per_batch} must be at least 1: give "
                "--pipeline.datamanager.sam-points-per-batch (ns-train) or --sam-points-per-batch (votesplat masks) a "
                "positive number, e.g. 256"
            )
        if max_long_side is not None and max_long_side < 16:
            raise VoteSplatInputError(f"max_long_side={max_long_side} is too small; use >= 16 or None")
        self.model_type = model_type
        self.device = device
        self.max_long_side = max_long_side
        self.generator_kwargs: Dict[str, Any] = dict(
            points_per_side=int(points_per_side),
            points_per_batch=int(points_per_batch),
            pred_iou_thresh=float(pred_iou_thresh),
            stability_score_thresh=float(stability_score_thresh),
            box_nms_thresh=float(box_nms_thresh),
            crop_n_layers=int(crop_n_layers),
            crop_n_points_downscale_factor=int(crop_n_points_downscale_factor),
            min_mask_region_area=int(min_mask_region_area),
            precision=precision,
            decoder=DEFAULT_DECODER,
        )
        # on a GPU only (SamSteps); not part of config_key: it changes float rounding, not what is computed
        self.compile_decoder = bool(compile_decoder)
        self._sam_model = sam_model
        self._generator = None
        self._generator_lock = threading.Lock()
        if sam_model is not None:
            self.checkpoint = None
            self._model_identity = {"model": "in-memory", "parameters_sha256": _state_dict_digest(sam_model)}
        else:
            self.checkpoint = check_sam_checkpoint(checkpoint, model_type)
            self._model_identity = {
                "model": model_type,
                "checkpoint_name": self.checkpoint.name,
                "checkpoint_bytes": self.checkpoint.stat().st_size,
                "checkpoint_sample_sha256": _sampled_digest(self.checkpoint),
            }

    def config_key(self) -> Dict[str, Any]:
        return {
            "type": "sam",
            "levels": list(self.levels),
            "max_long_side": self.max_long_side,
            **self._model_identity,
            **self.generator_kwargs,
        }

    def __getstate__(self) -> Dict[str, Any]:
        # sent to another process (vote_cache_ranks) without the generator: it holds the encoder's last features
        state = dict(self.__dict__)
        state["_generator"] = None
        del state["_generator_lock"]
        return state

    def __setstate__(self, state: Dict[str, Any]) -> None:
        vars(self).update(state, _generator_lock=threading.Lock())

    def on_device(self, device: str) -> "SamMaskSource":
        """A copy that runs SAM on ``device`` (its model is built there at the first image)."""
        moved = copy.copy(self)
        moved.device = device
        moved._generator = None
        moved._generator_lock = threading.Lock()
        return moved

    def _resolve_device(self) -> str:
        if self.device:
            return self.device
        import torch

        return "cuda" if torch.cuda.is_available() else "cpu"

    def _build_generator(self):
        import torch
        from segment_anything import SamPredictor, sam_model_registry

        if self._sam_model is None:
            assert self.checkpoint is not None  # __init__ checks one whenever no sam_model is given
            try:
                # loaded before the model is built, so a wrong file fails fast
                state_dict = torch.load(self.checkpoint, map_location="cpu", weights_only=True)
                model = sam_model_registry[self.model_type](checkpoint=None)
                model.load_state_dict(state_dict)
            except Exception as error:
                raise VoteSplatInputError(
                    f"could not load SAM checkpoint {self.checkpoint} as model type '{self.model_type}' ({load_failure_reason(error, self.checkpoint)}); "
                    f"expected the official {SAM_CHECKPOINT_FILES[self.model_type]} from the segment-anything "
                    "repository's README (facebookresearch/segment-anything)"
                ) from error
            self._sam_model = model
        self._sam_model.to(self._resolve_device()).eval()
        return SamLevelsMaskGenerator(
            SamPredictor(self._sam_model), self.levels, **self.generator_kwargs, compile_decoder=self.compile_decoder
        )

    def masks_for_image(self, image: np.ndarray, image_path: PathLike, frame_index: int) -> List[np.ndarray]:
        image = _as_rgb_uint8(image, image_path)
        with self._generator_lock:
            if self._generator is None:
                self._generator = self._build_generator()
        return self._generator.label_images(_limit_long_side(image, self.max_long_side))


class SamCropState:
    """What the encoder leaves for one crop: its features and the sizes ``SamPredictor`` keeps with them."""

    __slots__ = ("features", "original_size", "input_size")

    def __init__(self, features: Any, original_size: Tuple[int, int], input_size: Tuple[int, int]):
        self.features, self.original_size, self.input_size = features, original_size, input_size


class SamSteps:
    """segment_anything's ``SamPredictor`` cut into the three steps that :class:`SamLevelsMaskGenerator` runs apart.

    - ``encode_crops``: the image encoder per crop, as ``SamPredictor.set_image``; ``crops_per_encoder_pass``
      crops per encoder call (``None``: one in fp32, the encoder call segment_anything makes, so that the features
      are its bits, which a batched call need not give; all crops of the image in tf32 and bf16);
    - ``decode_points``: prompt encoder and mask decoder on a batch of point prompts, all three outputs: the
      low-resolution logits and the predicted IoUs (``SamPredictor.predict_torch`` up to ``postprocess_masks``);
    - ``upscale_masks``: ``Sam.postprocess_masks`` on some of those low-resolution logits. Its interpolations
      compute every output pixel from the input alone, so a mask upscaled in any batch has the bits it has in
      ``predict_torch``'s batch;
    - ``stability_and_boxes``: the stability scores and boxes of upscaled logits (:func:`stability_and_boxes`).

    ``precision`` (:data:`SAM_PRECISIONS`): ``"tf32"`` and ``"bf16"`` apply to encoder and decoder (their outputs
    come back as float32); the upscaling stays float32.

    ``decoder`` (``core/sam_decoder.py`` :data:`DECODER_MODES`): ``"folded"`` (default) runs segment_anything's
    decoder modules on one copy of the image tokens where they do not depend on the prompt, instead of one copy
    per prompt, and moves the later blocks' image-token projections onto the prompt's 7 tokens (BENCHMARKS.md
    "SAM masks": the labels stay segment_anything's); ``"shared"`` does only the first; ``"segment_anything"``
    calls ``MaskDecoder`` itself.

    ``compile_decoder``: on a CUDA device, the decoder runs through ``torch.compile`` (its elementwise work and
    normalisations fused: BENCHMARKS.md "SAM masks"), compiled once per process and prompt count; a short batch
    is padded to the longest one so far (prompts do not interact), so that it reuses that compilation. The
    stability scores and boxes are compiled too, once for all sizes. If a compilation fails, one warning says so
    and both run uncompiled. Not used on a CPU.
    """

    def __init__(
        self,
        predictor: Any,
        precision: str = "fp32",
        crops_per_encoder_pass: Optional[int] = None,
        decoder: str = DEFAULT_DECODER,
        compile_decoder: bool = False,
    ):
        import torch

        if decoder not in DECODER_MODES:
            raise VoteSplatInputError(f"unknown SAM decoder '{decoder}'; use one of {list(DECODER_MODES)}")
        self.decoder = decoder
        if precision not in SAM_PRECISIONS:
            raise VoteSplatInputError(f"unknown SAM precision '{precision}'; use one of {list(SAM_PRECISIONS)}")
        if crops_per_encoder_pass is not None and crops_per_encoder_pass < 1:
            raise VoteSplatInputError(f"crops_per_encoder_pass={crops_per_encoder_pass} must be >= 1 (or None)")
        self.predictor = predictor
        self.model = predictor.model
        self.transform = predictor.transform
        self.device = torch.device(predictor.device)
        self.mask_threshold = float(self.model.mask_threshold)
        self.precision = precision
        self.crops_per_encoder_pass = crops_per_encoder_pass
        self.compile_decoder = bool(compile_decoder) and self.device.type == "cuda"
        self._compiled_prompts = 0
        self._compiled_for: set = set()  # prompt counts whose compilation is done
        # held while a crop is encoded: SamPredictor keeps the image it encodes (set_image), so two threads'
        # images take turns there; decode_points and upscale_masks keep nothing and run side by side
        self.encoder_lock = threading.Lock()
        if precision == "bf16" and self.device.type == "cuda" and not torch.cuda.is_bf16_supported():
            raise VoteSplatInputError(
                f"SAM precision bf16 needs a GPU with bfloat16 (compute capability 8.0 or newer), not "
                f"{torch.cuda.get_device_name(self.device)}; use fp32"
            )

    def _autocast(self):
        import torch

        if self.precision == "bf16":
            return torch.autocast(device_type=self.device.type, dtype=torch.bfloat16)
        if self.precision == "tf32":
            return _float32_matmul_precision("high")
        return nullcontext()

    def encode_crops(self, crops: Sequence[np.ndarray]) -> List[SamCropState]:
        """The features of each RGB uint8 crop."""
        with self.encoder_lock:
            return self._encode_crops(crops)

    def _encode_crops(self, crops: Sequence[np.ndarray]) -> List[SamCropState]:
        import torch

        states: List[SamCropState] = []
        step = self.crops_per_encoder_pass or (1 if self.precision == "fp32" else max(1, len(crops)))
        for start in range(0, len(crops), step):
            group = crops[start : start + step]
            with self._autocast():
                if len(group) == 1:
                    self.predictor.set_image(group[0])
                    states.append(
                        SamCropState(self.predictor.features, self.predictor.original_size, self.predictor.input_size)
                    )
                    self.predictor.reset_image()
                    continue
                inputs, sizes = [], []
                for crop in group:  # SamPredictor.set_image and set_torch_image, the encoder call left out
                    if self.model.image_format != "RGB":
                        crop = crop[..., ::-1]
                    transformed = torch.as_tensor(self.transform.apply_image(crop), device=self.device)
                    transformed = transformed.permute(2, 0, 1).contiguous()[None, :, :, :]
                    sizes.append((tuple(crop.shape[:2]), tuple(transformed.shape[-2:])))
                    inputs.append(self.model.preprocess(transformed))
                features = self.model.image_encoder(torch.cat(inputs))
            for i, (original_size, input_size) in enumerate(sizes):
                states.append(SamCropState(features[i : i + 1], original_size, input_size))
        return states

    def decode_points(self, state: SamCropState, points: np.ndarray):
        """Low-resolution logits [P, 3, 256, 256] and predicted IoUs [P, 3] of P point prompts (crop pixels, x y)."""
        import torch

        from votesplat_ns.core.sam_decoder import decode_multimask

        transformed = self.transform.apply_coords(points, state.original_size)
        in_points = torch.as_tensor(transformed, device=self.device)
        in_labels = torch.ones(in_points.shape[0], dtype=torch.int, device=self.device)
        with self._autocast():
            sparse, dense = self.model.prompt_encoder(
                points=(in_points[:, None, :], in_labels[:, None]), boxes=None, masks=None
            )
            arguments = (self.model.mask_decoder, state.features, self.model.prompt_encoder.get_dense_pe())
            if self.compile_decoder:
                low_res, iou_predictions = self._decode_compiled(*arguments, sparse, dense)
            else:
                low_res, iou_predictions = decode_multimask(*arguments, sparse, dense, self.decoder)
        return low_res.float(), iou_predictions.float()

    def _decode_compiled(self, mask_decoder: Any, features: Any, image_pe: Any, sparse: Any, dense: Any):
        """``decode_multimask`` through ``torch.compile``, ``sparse`` padded to the most prompts compiled for."""
        import torch

        from votesplat_ns.core.sam_decoder import decode_multimask

        prompts = sparse.shape[0]
        self._compiled_prompts = max(self._compiled_prompts, prompts)
        if prompts < self._compiled_prompts:
            padding = self._compiled_prompts - prompts
            sparse = torch.cat([sparse, sparse[-1:].expand(padding, -1, -1)])
            if dense.shape[0] == prompts > 1:  # the prompt encoder's no-mask embedding, one per prompt
                dense = torch.cat([dense, dense[-1:].expand(padding, -1, -1, -1)])
        arguments = (mask_decoder, features, image_pe, sparse, dense, self.decoder)
        compiled = self._compiled(_compiled_decode_multimask(), sparse.shape[0], "decoder", *arguments)
        if compiled is None:
            return decode_multimask(
                mask_decoder, features, image_pe, sparse[:prompts], dense[: max(1, prompts)], self.decoder
            )
        low_res, iou_predictions = compiled
        return low_res[:prompts], iou_predictions[:prompts]

    def upscale_masks(self, state: SamCropState, low_res: Any):
        """Mask logits [m, h, w] at the crop's size from m rows [m, 256, 256] of ``decode_points``' logits."""
        return self.model.postprocess_masks(low_res[:, None], state.input_size, state.original_size)[:, 0]

    def stability_and_boxes(self, logits: Any, stability_offset: float):
        """:func:`stability_and_boxes` of mask logits [m, h, w] at this model's mask threshold; with
        ``compile_decoder`` on CUDA through ``torch.compile`` (one pass over the logits instead of six: the
        same integers)."""
        arguments = (logits, self.mask_threshold, float(stability_offset))
        counted = None
        if self.compile_decoder:
            counted = self._compiled(
                _compiled_stability_counts_and_boxes(), "stability", "stability scores", *arguments
            )
        intersections, unions, boxes = counted if counted is not None else stability_counts_and_boxes(*arguments)
        return intersections / unions, boxes  # divided outside the graph: inductor's division need not round as torch's

    def _compiled(self, function: Any, key: Any, what: str, *arguments: Any):
        """``function(*arguments)``, compiled by ``torch.compile``: its first call per ``key`` (one compilation)
        one thread at a time; ``None`` after one warning naming ``what`` if it cannot compile (``compile_decoder``
        is then off, for the decoder and the stability scores alike)."""
        import warnings

        try:
            if key in self._compiled_for:
                return function(*arguments)
            with _COMPILE_LOCK, warnings.catch_warnings():  # one thread at a time, so also one in the filter
                warnings.filterwarnings("ignore", message=".*[Oo]nline softmax")  # inductor's note on its choice
                result = function(*arguments)
            self._compiled_for.add(key)
            return result
        except Exception as error:  # a missing compiler, an unsupported GPU: the functions as they are
            warnings.warn(
                f"SAM's {what} could not be compiled ({type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}); "
                "running the decoder and the stability scores uncompiled (slower; the masks are the same up to float "
                "rounding)"
            )
            self.compile_decoder = False
            return None


_COMPILE_LOCK = threading.Lock()


@functools.lru_cache(maxsize=None)
def _compiled_decode_multimask() -> Any:
    """``decode_multimask`` through ``torch.compile``, one wrapper per process (its compilations are kept per
    model, precision and prompt count)."""
    import torch

    from votesplat_ns.core.sam_decoder import decode_multimask

    return torch.compile(decode_multimask, dynamic=False)


@functools.lru_cache(maxsize=None)
def _compiled_stability_counts_and_boxes() -> Any:
    """:func:`stability_counts_and_boxes` through ``torch.compile``, its sizes symbolic: one compilation for every
    chunk and crop size."""
    import torch

    return torch.compile(stability_counts_and_boxes, dynamic=True)


def stability_and_boxes(logits: Any, mask_threshold: float, stability_offset: float):
    """segment_anything's ``calculate_stability_score(logits, mask_threshold, stability_offset)`` [m] and
    ``batched_mask_to_box(logits > mask_threshold)`` [m, 4] (int64) of mask logits [m, h, w], the same values."""
    intersections, unions, boxes = stability_counts_and_boxes(logits, mask_threshold, stability_offset)
    return intersections / unions, boxes


def stability_counts_and_boxes(logits: Any, mask_threshold: float, stability_offset: float):
    """The pixel counts of a stability score (above ``mask_threshold`` plus and minus ``stability_offset``; int32
    [m]) and the boxes of :func:`stability_and_boxes`. Integers, so the same whatever order they are reduced in
    (segment_anything counts a row in int16, exact below 32768 columns). Written as reductions of the logits that
    ``torch.compile`` fuses, so that no thresholded [m, h, w] mask is made."""
    import torch

    m, h, w = logits.shape
    intersections = (logits > mask_threshold + stability_offset).sum((-2, -1), dtype=torch.int32)
    unions = (logits > mask_threshold - stability_offset).sum((-2, -1), dtype=torch.int32)
    above = logits > mask_threshold
    in_height, in_width = above.any(-1), above.any(-2)  # [m, h], [m, w]
    rows = torch.arange(h, device=logits.device)
    columns = torch.arange(w, device=logits.device)
    bottom = (in_height * rows).amax(-1)
    top = torch.where(in_height, rows, h).amin(-1)
    right = (in_width * columns).amax(-1)
    left = torch.where(in_width, columns, w).amin(-1)
    empty = (right < left) | (bottom < top)  # an empty mask's box is [0, 0, 0, 0]
    boxes = torch.stack([left, top, right, bottom], dim=-1) * (~empty)[:, None]
    return intersections, unions, boxes


_MATMUL_PRECISION_LOCK = threading.Lock()
_matmul_precision_users: List[Any] = []  # [count, the precision before the first] while some thread is inside


@contextmanager
def _float32_matmul_precision(precision: str) -> Iterator[None]:
    """``torch.set_float32_matmul_precision`` while some thread is inside (it is global: the precision from
    before the first thread entered is restored when the last one leaves)."""
    import torch

    with _MATMUL_PRECISION_LOCK:
        if not _matmul_precision_users:
            _matmul_precision_users[:] = [0, torch.get_float32_matmul_precision()]
            torch.set_float32_matmul_precision(precision)
        _matmul_precision_users[0] += 1
    try:
        yield
    finally:
        with _MATMUL_PRECISION_LOCK:
            _matmul_precision_users[0] -= 1
            if _matmul_precision_users[0] == 0:
                torch.set_float32_matmul_precision(_matmul_precision_users[1])
                _matmul_precision_users.clear()


class _Crop:
    """A crop after its filters: per level the kept masks (segment_anything's ``MaskData``), and the
    low-resolution logits of the masks some level keeps (``rows``: their indices among the crop's masks)."""

    __slots__ = ("state", "crop_box", "levels", "rows", "low_res")

    def __init__(self, state, crop_box, levels, rows, low_res):
        self.state, self.crop_box, self.levels, self.rows, self.low_res = state, crop_box, levels, rows, low_res


class SamLevelsMaskGenerator:
    """segment_anything's ``SamAutomaticMaskGenerator`` for several granularity levels in one pass.

    Per image the encoder runs once per crop (:class:`SamSteps`, or crops batched), and the prompt decoder once
    per batch of ``points_per_batch`` prompts, keeping all three multimask outputs as low-resolution logits.
    Each level takes its masks from that one set (``"s"``, ``"m"``, ``"l"``: output 0, 1, 2; ``"default"``: all
    three, in the generator's point-major order) and goes through segment_anything's own filters: predicted IoU,
    stability score, crop-edge boxes, box NMS within the crop, NMS across crops, small-region removal with its
    NMS. Every filter calls the same segment_anything/torchvision function on the same values in the same order
    as ``SamAutomaticMaskGenerator`` run once per level (configured the same, ``points_per_batch`` included, and in
    fp32 one crop per encoder call, so that the model's calls are its calls), so ties break the same way and the
    label images are the same.

    What is not repeated: the encoder and decoder per level; the upscaling of a mask below the predicted IoU
    threshold (that filter does not look at the mask); the per-mask quantities, computed once on the device for
    all levels, ``UPSCALE_BUDGET_BYTES`` of masks at a time; the RLE round trip. A crop keeps, on the device, only
    the low-resolution logits of the masks its NMS keeps; after the NMS across crops the survivors are upscaled
    again (the same bits), packed to bits and moved to the host in one copy per crop, each kept as its
    bounding-box window (``rle_to_mask(mask_to_rle(m)) == m``). Nothing in the decoder batches waits for the
    device; a crop's filters read back a few small results (the masks' counts, outputs, each level's NMS), the
    NMS across crops its kept indices. The small-region clean-up runs once per mask,
    however many levels keep it, in the mask's box rather than the whole image (:func:`_small_regions_removed`,
    same result), on ``workers`` threads.

    ``predictor``: a ``SamPredictor`` (run by :class:`SamSteps` with ``precision``, ``crops_per_encoder_pass``,
    ``decoder`` and ``compile_decoder``),
    or an object with ``SamSteps``' ``encode_crops`` / ``decode_points`` / ``upscale_masks`` /
    ``stability_and_boxes`` / ``device`` / ``mask_threshold``, used as it is. Set ``stage_seconds = {}`` to
    accumulate seconds per stage (the device is synchronised at each stage boundary then, so only for measuring).
    """

    def __init__(
        self,
        predictor: Any,
        levels: Sequence[str],
        points_per_side: int = 32,
        points_per_batch: int = DEFAULT_POINTS_PER_BATCH,
        pred_iou_thresh: float = 0.88,
        stability_score_thresh: float = 0.95,
        stability_score_offset: float = 1.0,
        box_nms_thresh: float = 0.7,
        crop_n_layers: int = 0,
        crop_nms_thresh: float = 0.7,
        crop_overlap_ratio: float = 512 / 1500,
        crop_n_points_downscale_factor: int = 1,
        min_mask_region_area: int = 0,
        precision: str = "fp32",
        crops_per_encoder_pass: Optional[int] = None,
        upscale_budget_bytes: int = UPSCALE_BUDGET_BYTES,
        workers: Optional[int] = None,
        decoder: str = DEFAULT_DECODER,
        compile_decoder: bool = False,
    ):
        from segment_anything.utils.amg import build_all_layer_point_grids

        unknown = [level for level in levels if level not in _OUTPUT_INDEX]
        if unknown:
            raise VoteSplatInputError(f"unknown SAM mask levels {unknown}; use a subset of {list(SAM_LEVELS)}")
        if points_per_batch < 1:
            raise VoteSplatInputError(f"points_per_batch={points_per_batch} must be >= 1")
        if hasattr(predictor, "decode_points"):
            self.steps = predictor
        else:
            self.steps = SamSteps(predictor, precision, crops_per_encoder_pass, decoder, compile_decoder)
        self.levels = tuple(levels)
        self.point_grids = build_all_layer_point_grids(points_per_side, crop_n_layers, crop_n_points_downscale_factor)
        self.points_per_batch = points_per_batch
        self.pred_iou_thresh = pred_iou_thresh
        self.stability_score_thresh = stability_score_thresh
        self.stability_score_offset = stability_score_offset
        self.box_nms_thresh = box_nms_thresh
        self.crop_n_layers = crop_n_layers
        self.crop_nms_thresh = crop_nms_thresh
        self.crop_overlap_ratio = crop_overlap_ratio
        self.min_mask_region_area = min_mask_region_area
        self.upscale_budget_bytes = upscale_budget_bytes
        self.workers = workers if workers is not None else min(8, os.cpu_count() or 1)
        self.stage_seconds: Optional[Dict[str, float]] = None

    @contextmanager
    def _stage(self, name: str) -> Iterator[None]:
        if self.stage_seconds is None:
            yield
            return
        self._synchronize()
        start = time.perf_counter()
        yield
        self._synchronize()
        self.stage_seconds[name] = self.stage_seconds.get(name, 0.0) + time.perf_counter() - start

    def _synchronize(self) -> None:
        import torch

        device = torch.device(self.steps.device)
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    def _chunk(self, crop_size: Tuple[int, int]) -> int:
        """Masks per upscaling call at a crop's size (:data:`UPSCALE_BUDGET_BYTES`)."""
        per_mask = 4 * 1024 * 1024 + 8 * crop_size[0] * crop_size[1]
        return max(1, self.upscale_budget_bytes // per_mask)

    def label_images(self, image: np.ndarray) -> List[np.ndarray]:
        """One int32 label image per level for an RGB uint8 [H, W, 3] image (0: no mask).

        Threads may call it at once (the cache build runs two): the encoder runs for one image at a time (the
        predictor holds its image), everything else of two images side by side, so that the device works on one
        image while the host works on the other (their filters, small regions and labels). Labels do not depend on
        that order."""
        import torch

        # tf32's matmul precision is global, and torch.compile's graphs guard on it: held over the whole image (its
        # filters do no float32 matmul), two threads never flip it under each other's compiled graphs
        tf32 = _float32_matmul_precision("high") if getattr(self.steps, "precision", None) == "tf32" else nullcontext()
        with torch.no_grad(), tf32:
            return self._label_images(image)

    def _label_images(self, image: np.ndarray) -> List[np.ndarray]:
        import torch
        from segment_anything.utils.amg import MaskData, generate_crop_boxes
        from torchvision.ops.boxes import batched_nms, box_area

        orig_size = (int(image.shape[0]), int(image.shape[1]))
        crop_boxes, layer_idxs = generate_crop_boxes(orig_size, self.crop_n_layers, self.crop_overlap_ratio)
        with self._stage("encoder"):
            states = self.steps.encode_crops([image[y0:y1, x0:x1, :] for x0, y0, x1, y1 in crop_boxes])
        crops = [
            self._process_crop(index, state, crop_box, layer_idx, orig_size)
            for index, (state, crop_box, layer_idx) in enumerate(zip(states, crop_boxes, layer_idxs))
        ]
        del states

        kept: Dict[str, List[Tuple[int, int]]] = {}
        with self._stage("nms"):
            for level in self.levels:
                data = MaskData()
                for crop in crops:
                    data.cat(crop.levels[level])
                # SamAutomaticMaskGenerator._generate_masks: duplicates between crops, smaller crops preferred;
                # skipped without masks (segment_anything 1.0's box_area fails on the empty 1-D tensor there)
                if len(crop_boxes) > 1 and len(data["rows"]) > 0:
                    scores = 1 / box_area(data["crop_boxes"])
                    scores = scores.to(data["boxes"].device)
                    keep_by_nms = batched_nms(
                        data["boxes"].float(),
                        scores,
                        torch.zeros(len(data["boxes"])),
                        iou_threshold=self.crop_nms_thresh,
                    )
                    data.filter(keep_by_nms)
                kept[level] = list(zip(data["crop_index"].tolist(), data["rows"].tolist()))

        with self._stage("masks"):
            windows = self._kept_windows(crops, kept, orig_size)
        del crops
        with self._stage("small_regions"):
            if self.min_mask_region_area > 0:
                every_key = sorted({key for keys in kept.values() for key in keys})
                windows.clean(every_key, self.min_mask_region_area, self.workers)
            masks = {
                level: self._remove_small_regions(keys, windows)
                if self.min_mask_region_area > 0 and keys
                else [windows.original(key) for key in keys]
                for level, keys in kept.items()
            }
        with self._stage("paint"):
            return [_paint_windows(masks[level], orig_size) for level in self.levels]

    def _process_crop(self, crop_index: int, state, crop_box, layer_idx: int, orig_size) -> _Crop:
        """SamAutomaticMaskGenerator._process_crop and _process_batch for every level: the crop's masks that each
        level keeps, with the low-resolution logits of those masks."""
        import torch
        from segment_anything.utils.amg import MaskData, is_box_near_crop_edge, uncrop_boxes_xyxy
        from torchvision.ops.boxes import batched_nms

        x0, y0, x1, y1 = crop_box
        crop_size = (y1 - y0, x1 - x0)
        points_for_image = self.point_grids[layer_idx] * np.array(crop_size)[None, ::-1]
        with self._stage("decoder"):
            low_res, iou = [], []
            for start in range(0, len(points_for_image), self.points_per_batch):
                batch_low_res, batch_iou = self.steps.decode_points(
                    state, points_for_image[start : start + self.points_per_batch]
                )
                low_res.append(batch_low_res.flatten(0, 1))  # point-major, as the generator's flatten(0, 1)
                iou.append(batch_iou.flatten(0, 1))
                n_outputs = batch_iou.shape[1]
            low_res = torch.cat(low_res) if len(low_res) > 1 else low_res[0]
            iou = torch.cat(iou) if len(iou) > 1 else iou[0]

        with self._stage("filter"):
            device = iou.device
            # predicted IoU first: it does not look at the mask, so a mask below it is never upscaled
            if self.pred_iou_thresh > 0.0:
                rows = torch.nonzero(iou > self.pred_iou_thresh).flatten()
            else:
                rows = torch.arange(len(iou), device=device)
            stability, boxes = [], []
            for chunk in torch.split(rows, self._chunk(crop_size)) if len(rows) else ():
                logits = self.steps.upscale_masks(state, low_res[chunk])
                chunk_stability, chunk_boxes = self.steps.stability_and_boxes(logits, self.stability_score_offset)
                stability.append(chunk_stability)
                boxes.append(chunk_boxes)
                del logits
            if stability:
                stability_all, boxes_all = torch.cat(stability), torch.cat(boxes)
            else:
                stability_all = torch.zeros(0, device=device)
                boxes_all = torch.zeros(0, 4, dtype=torch.long, device=device)
            keep = ~is_box_near_crop_edge(boxes_all, crop_box, [0, 0, orig_size[1], orig_size[0]])
            if self.stability_score_thresh > 0.0:
                keep &= stability_all >= self.stability_score_thresh
            kept = torch.nonzero(keep).flatten()
            rows, boxes_all = rows[kept], boxes_all[kept]
            iou_kept = iou[rows]
            outputs = (rows % n_outputs).cpu().numpy()

        levels: Dict[str, Any] = {}
        with self._stage("nms"):
            for level in self.levels:
                index = _OUTPUT_INDEX[level]
                if index is None:
                    level_rows, level_boxes, level_iou = rows, boxes_all, iou_kept
                else:
                    select = torch.as_tensor(np.flatnonzero(outputs == index), device=device)
                    level_rows, level_boxes, level_iou = rows[select], boxes_all[select], iou_kept[select]
                # remove duplicates within this crop (SamAutomaticMaskGenerator._process_crop)
                keep_by_nms = batched_nms(
                    level_boxes.float(),
                    level_iou,
                    torch.zeros(len(level_boxes)),
                    iou_threshold=self.box_nms_thresh,
                )
                count = len(keep_by_nms)
                levels[level] = MaskData(
                    rows=level_rows[keep_by_nms],
                    boxes=uncrop_boxes_xyxy(level_boxes[keep_by_nms], crop_box),
                    crop_boxes=torch.tensor([crop_box for _ in range(count)]),
                    crop_index=torch.full((count,), crop_index, dtype=torch.long),
                )
            union = torch.unique(torch.cat([data["rows"] for data in levels.values()]))
            return _Crop(state, crop_box, levels, union, low_res[union])

    def _kept_windows(self, crops: List[_Crop], kept: Dict[str, List[Tuple[int, int]]], orig_size) -> "_MaskWindows":
        """The masks that some level keeps, upscaled again from their logits, as windows on the host."""
        import torch
        from segment_anything.utils.amg import batched_mask_to_box

        windows = _MaskWindows(orig_size)
        wanted: Dict[int, List[int]] = {}
        for crop_index, row in sorted({key for keys in kept.values() for key in keys}):
            wanted.setdefault(crop_index, []).append(row)
        threshold = self.steps.mask_threshold
        for crop_index, rows in wanted.items():
            crop = crops[crop_index]
            x0, y0, x1, y1 = crop.crop_box
            positions = torch.searchsorted(crop.rows, torch.as_tensor(rows, device=crop.rows.device))
            packed, boxes = [], []
            for chunk in torch.split(positions, self._chunk((y1 - y0, x1 - x0))):
                masks = self.steps.upscale_masks(crop.state, crop.low_res[chunk]) > threshold
                boxes.append(batched_mask_to_box(masks))
                packed.append(_packed_bits(masks))
                del masks
            host_packed = torch.cat(packed).cpu().numpy()
            host_boxes = torch.cat(boxes).long().cpu().numpy()
            for row, mask_bits, box in zip(rows, host_packed, host_boxes):
                windows.add_packed((crop_index, row), mask_bits, box, (x0, y0))
        return windows

    def _remove_small_regions(self, keys: List[Tuple[int, int]], windows: "_MaskWindows") -> List["_Window"]:
        """SamAutomaticMaskGenerator.postprocess_small_regions on one level's masks, in its order."""
        import torch
        from torchvision.ops.boxes import batched_nms

        cleaned = [windows.cleaned(key, self.min_mask_region_area) for key in keys]
        boxes = torch.stack([torch.as_tensor(window.box_xyxy()) for window, _ in cleaned])
        scores = [float(unchanged) for _, unchanged in cleaned]
        keep_by_nms = batched_nms(
            boxes.float(),
            torch.as_tensor(scores),
            torch.zeros(len(boxes)),
            iou_threshold=max(self.box_nms_thresh, self.crop_nms_thresh),
        )
        return [cleaned[int(i)][0] for i in keep_by_nms]


def _packed_bits(masks: Any) -> Any:
    """Boolean masks [m, h, w] as uint8 [m, h, ceil(w / 8)], eight columns a byte, the first in the high bit (np.packbits)."""
    import torch

    m, h, w = masks.shape
    values = masks.to(torch.uint8)
    if w % 8:
        values = torch.nn.functional.pad(values, (0, 8 - w % 8))
    weights = torch.tensor([128, 64, 32, 16, 8, 4, 2, 1], dtype=torch.uint8, device=masks.device)
    return (values.view(m, h, -1, 8) * weights).sum(-1, dtype=torch.uint8)


class _Window:
    """A binary mask of the whole image held as its bounding-box window: rows y0.., columns x0.."""

    __slots__ = ("x0", "y0", "mask")

    def __init__(self, x0: int, y0: int, mask: np.ndarray):
        self.x0, self.y0, self.mask = x0, y0, mask

    def area(self) -> int:
        return int(np.count_nonzero(self.mask))

    def box_xyxy(self) -> np.ndarray:
        """batched_mask_to_box's box (inclusive max corner; zeros for an empty mask)."""
        rows = np.flatnonzero(self.mask.any(axis=1))
        cols = np.flatnonzero(self.mask.any(axis=0))
        if rows.size == 0:
            return np.zeros(4, dtype=np.int64)
        return np.array([self.x0 + cols[0], self.y0 + rows[0], self.x0 + cols[-1], self.y0 + rows[-1]], dtype=np.int64)

    def full(self, shape: Tuple[int, int]) -> np.ndarray:
        out = np.zeros(shape, dtype=bool)
        h, w = self.mask.shape
        out[self.y0 : self.y0 + h, self.x0 : self.x0 + w] = self.mask
        return out

    @staticmethod
    def of_window(x0: int, y0: int, mask: np.ndarray) -> "_Window":
        """The window of a mask given on a window at (x0, y0), trimmed to its bounding box."""
        trimmed = _Window.of(mask)
        return _Window(x0 + trimmed.x0, y0 + trimmed.y0, trimmed.mask)

    @staticmethod
    def of(mask: np.ndarray) -> "_Window":
        rows = np.flatnonzero(mask.any(axis=1))
        cols = np.flatnonzero(mask.any(axis=0))
        if rows.size == 0:
            return _Window(0, 0, np.zeros((0, 0), dtype=bool))
        y0, y1, x0, x1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
        return _Window(int(x0), int(y0), np.ascontiguousarray(mask[y0:y1, x0:x1]))


class _MaskWindows:
    """The masks some level keeps, by key, as windows on the host (unpacked from their bits when first asked for,
    on the thread that asks); their small-region clean-ups."""

    def __init__(self, shape: Tuple[int, int]):
        self.shape = shape
        self._packed: Dict[Any, Tuple[np.ndarray, np.ndarray, Tuple[int, int]]] = {}
        self._windows: Dict[Any, _Window] = {}
        self._cleaned: Dict[Any, Tuple[_Window, bool]] = {}

    def add_packed(self, key: Any, mask_bits: np.ndarray, box: np.ndarray, offset: Tuple[int, int]) -> None:
        """A crop's mask from its packed bits [h, ceil(w / 8)] and its box in the crop (batched_mask_to_box)."""
        self._packed[key] = (mask_bits, box, offset)

    def original(self, key: Any) -> _Window:
        window = self._windows.get(key)
        if window is None:
            mask_bits, box, offset = self._packed[key]
            bx0, by0, bx1, by1 = (int(v) for v in box)
            rows = np.unpackbits(mask_bits[by0 : by1 + 1, bx0 // 8 : bx1 // 8 + 1], axis=-1)
            mask = np.ascontiguousarray(rows[:, bx0 % 8 : bx0 % 8 + bx1 - bx0 + 1]).view(bool)
            window = self._windows[key] = _Window(offset[0] + bx0, offset[1] + by0, mask)
        return window

    def clean(self, keys: Sequence[Any], min_area: int, workers: int = 1) -> None:
        """Compute the clean-ups of ``keys`` ahead, on ``workers`` threads (OpenCV and numpy release the GIL)."""
        todo = [key for key in keys if key not in self._cleaned]

        def cleaned(key: Any) -> Tuple[_Window, bool]:
            return _small_regions_removed(self.original(key), self.shape, min_area)

        if workers > 1 and len(todo) > 1:
            from concurrent.futures import ThreadPoolExecutor

            with ThreadPoolExecutor(max_workers=workers) as pool:
                results = list(pool.map(cleaned, todo))
        else:
            results = [cleaned(key) for key in todo]
        self._cleaned.update(zip(todo, results))

    def cleaned(self, key: Any, min_area: int) -> Tuple[_Window, bool]:
        """segment_anything's hole then island removal of one mask, and whether it left the mask unchanged."""
        saved = self._cleaned.get(key)
        if saved is None:
            saved = _small_regions_removed(self.original(key), self.shape, min_area)
            self._cleaned[key] = saved
        return saved


def _small_regions_removed_whole_image(window: _Window, shape: Tuple[int, int], min_area: int) -> Tuple[_Window, bool]:
    """SamAutomaticMaskGenerator.postprocess_small_regions on one mask: segment_anything's routine on the whole image."""
    from segment_anything.utils.amg import remove_small_regions

    mask = window.full(shape)
    mask, changed = remove_small_regions(mask, min_area, mode="holes")
    unchanged = not changed
    mask, changed = remove_small_regions(mask, min_area, mode="islands")
    unchanged = unchanged and not changed
    return _Window.of(mask), unchanged


def _outside_pieces(box: Tuple[int, int, int, int], shape: Tuple[int, int]) -> List[int]:
    """Pixel counts of the connected pieces of the image outside a box (x0, y0, x1, y1 exclusive)."""
    x0, y0, x1, y1 = box
    height, width = shape
    top, bottom = y0 * width, (height - y1) * width
    left, right = (y1 - y0) * x0, (y1 - y0) * (width - x1)
    if (top or bottom) and (left or right):
        return [top + bottom + left + right]  # a side strip joins the top and bottom strips
    return [size for size in (top, bottom, left, right) if size]


def _small_regions_removed(window: _Window, shape: Tuple[int, int], min_area: int) -> Tuple[_Window, bool]:
    """The result of segment_anything's ``remove_small_regions`` (holes, then islands) on the whole image, computed
    in the mask's box grown by one pixel, so that its cost follows the mask's size, not the image's.

    Why it is the same: every pixel outside the box is background, so each connected piece of the image outside the
    box lies in one background component, reached through the one-pixel ring; a ring-touching component is at least
    as large as that piece, and when every piece has ``min_area`` pixels or more none of them is a small hole, as on
    the whole image. The other background components and all mask components lie inside the box, with the same
    pixels as on the whole image. segment_anything keeps the first largest island when all are small; labels are
    numbered in scan order, which a window could change, so a tie for the largest goes to the whole-image routine,
    as does a piece outside the box smaller than ``min_area``.
    """
    import cv2

    height, width = shape
    h, w = window.mask.shape
    x0, y0 = window.x0, window.y0
    if h == 0 or w == 0 or min(_outside_pieces((x0, y0, x0 + w, y0 + h), shape), default=min_area) < min_area:
        return _small_regions_removed_whole_image(window, shape, min_area)
    px0, py0 = max(0, x0 - 1), max(0, y0 - 1)
    px1, py1 = min(width, x0 + w + 1), min(height, y0 + h + 1)
    padded = np.zeros((py1 - py0, px1 - px0), dtype=bool)
    inner = (slice(y0 - py0, y0 - py0 + h), slice(x0 - px0, x0 - px0 + w))
    padded[inner] = window.mask

    # holes: background components inside the box smaller than min_area are filled
    _, regions, stats, _ = cv2.connectedComponentsWithStats((~padded).astype(np.uint8), connectivity=8)
    touching = np.zeros(len(stats), dtype=bool)
    # the ring: the rows and columns of the padded window outside the box (none on a side at the image's edge)
    for present, edge in (
        (py0 < y0, regions[0]),
        (py1 > y0 + h, regions[-1]),
        (px0 < x0, regions[:, 0]),
        (px1 > x0 + w, regions[:, -1]),
    ):
        if present:
            touching[edge] = True
    small = (stats[:, -1] < min_area) & ~touching
    small[0] = False  # label 0: the mask's own pixels
    mask = window.mask
    holes_changed = bool(small.any())
    if holes_changed:
        mask = mask | small[regions[inner]]

    # islands: mask components smaller than min_area are dropped, the largest one kept if all are
    _, regions, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    sizes = stats[1:, -1]
    small_islands = sizes < min_area
    if not small_islands.any():
        return _Window.of_window(x0, y0, mask), not holes_changed
    if small_islands.all() and np.count_nonzero(sizes == sizes.max()) > 1:
        return _small_regions_removed_whole_image(_Window(x0, y0, mask), shape, min_area)[0], False
    keep = np.zeros(len(stats), dtype=bool)
    if small_islands.all():
        keep[int(np.argmax(sizes)) + 1] = True
    else:
        keep[1:] = ~small_islands
    return _Window.of_window(x0, y0, keep[np.asarray(regions, dtype=np.int32)]), False


def _paint_windows(masks: List[_Window], shape: Tuple[int, int]) -> np.ndarray:
    """Label image with the rule of :func:`labels_from_binary_masks`: a smaller mask wins, then the earlier one."""
    labels = np.zeros(shape, dtype=np.int32)
    if not masks:
        return labels
    areas = np.array([window.area() for window in masks], dtype=np.int64)
    indices = np.arange(len(masks))
    for i in np.lexsort((-indices, -areas)):
        window = masks[i]
        h, w = window.mask.shape
        labels[window.y0 : window.y0 + h, window.x0 : window.x0 + w][window.mask] = i + 1
    return labels


def _as_rgb_uint8(image: np.ndarray, image_path: PathLike) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] not in (3, 4):
        raise VoteSplatInputError(f"image {image_path} must be uint8 [H, W, 3], got {image.dtype} {tuple(image.shape)}")
    return np.ascontiguousarray(image[..., :3])


def _limit_long_side(image: np.ndarray, max_long_side: Optional[int]) -> np.ndarray:
    height, width = image.shape[:2]
    if max_long_side is None or max(height, width) <= max_long_side:
        return image
    scale = max_long_side / max(height, width)
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    return np.asarray(Image.fromarray(image).resize(size, resample=Image.Resampling.BILINEAR))


def check_sam_checkpoint(checkpoint: Optional[PathLike], model_type: str) -> Path:
    """The checkpoint path if it is a readable file, else a one-line ValueError naming the expected file."""
    expected = SAM_CHECKPOINT_FILES[model_type]
    hint = (
        f"expected the SAM {model_type} checkpoint file {expected} (the official checkpoints are listed in the "
        "segment-anything repository's README, facebookresearch/segment-anything); it is never downloaded automatically"
    )
    if checkpoint is None or str(checkpoint) == "":
        raise VoteSplatInputError(f"no SAM checkpoint given: pass the path to {expected}; {hint}")
    path = Path(checkpoint).expanduser()
    if not path.is_file():
        raise VoteSplatInputError(f"SAM checkpoint {path} does not exist; {hint}")
    try:
        with open(path, "rb") as handle:
            handle.read(1)
    except OSError as error:
        raise VoteSplatInputError(f"SAM checkpoint {path} is not readable ({error.strerror}); {hint}") from error
    return path


def _sampled_digest(path: Path, sample: int = 1 << 20) -> str:
    """sha256 of a large file's size, first and last MiB (cheap identity for multi-GB checkpoints)."""
    size = path.stat().st_size
    digest = hashlib.sha256(str(size).encode())
    with open(path, "rb") as handle:
        digest.update(handle.read(sample))
        if size > sample:
            handle.seek(max(sample, size - sample))
            digest.update(handle.read(sample))
    return digest.hexdigest()


def _state_dict_digest(model: Any) -> str:
    digest = hashlib.sha256()
    for name, tensor in sorted(model.state_dict().items()):
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()
