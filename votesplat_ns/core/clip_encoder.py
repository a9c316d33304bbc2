"""The frozen image/text encoder of the semantic step (paper §3.4): open_clip weights from a local file.

:class:`EncoderProtocol` is what :mod:`votesplat_ns.core.semantics` needs from an encoder; its
``config`` names the feature space, and :func:`check_same_encoder` refuses features made in another.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any, Dict, Mapping, Protocol, Sequence, Union, runtime_checkable

import numpy as np
import torch
import torch.nn.functional as F

from votesplat_ns.errors import load_failure_reason

# The smallest open_clip 2.32 architecture whose config needs neither timm nor a Hugging Face
# text tower/tokenizer (vision ViT width 384 / patch 32, text width 256, 43 M parameters).
SMALLEST_OPEN_CLIP_MODEL = "ViT-S-32-alt"
# Keys of an encoder config that describe where weights came from, not what they are: a checkpoint
# copied to another folder is still the same feature space.
_PROVENANCE_KEYS = frozenset({"checkpoint_path"})


class CheckpointNotFoundError(FileNotFoundError, ValueError):
    """A CLIP checkpoint file that is not there (a FileNotFoundError that is also a ValueError)."""


@runtime_checkable
class EncoderProtocol(Protocol):
    """What the semantic code needs from an image/text encoder.

    ``config`` must be JSON-serialisable and identify the feature space: two encoders with equal
    configs (ignoring ``checkpoint_path``) must map the same input to the same feature. It is stored
    with instance features and checked when they are loaded or queried.
    """

    @property
    def config(self) -> Mapping[str, Any]: ...

    def encode_images(self, crops: Sequence[np.ndarray]) -> torch.Tensor:
        """HxWx3 uint8 crops -> [n, D] float32, rows of unit norm."""
        ...

    def encode_text(self, texts: Sequence[str]) -> torch.Tensor:
        """Strings -> [n, D] float32, rows of unit norm."""
        ...


def _sha256_of_file(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 22), b""):
            digest.update(block)
    return digest.hexdigest()


def _check_open_clip_model_name(model_name: str) -> None:
    import open_clip

    if model_name.startswith(("hf-hub:", "local-dir:")):
        raise ValueError(
            f"model_name {model_name!r} names a hub/directory model; pass an architecture name from "
            "open_clip.list_models() (e.g. 'ViT-B-16') and the weights file as checkpoint_path"
        )
    model_config = open_clip.get_model_config(model_name)
    if model_config is None:
        raise ValueError(
            f"unknown open_clip architecture {model_name!r}; pick one of open_clip.list_models(), e.g. 'ViT-B-16'"
        )
    text_config = model_config.get("text_cfg", {})
    if text_config.get("hf_model_name") or text_config.get("hf_tokenizer_name"):
        # Such models fetch a tokenizer/text tower from the Hugging Face hub at construction time.
        raise ValueError(
            f"open_clip architecture {model_name!r} needs a Hugging Face tokenizer or text model, which "
            "would be downloaded at run time; use an architecture with a built-in tokenizer such as 'ViT-B-16'"
        )


class ClipEncoder:
    """An open_clip model used as a frozen image/text encoder (implements :class:`EncoderProtocol`).

    Image crops go through the model's own preprocessing (resize shorter side, centre crop,
    normalise); callers that want the whole crop seen should pad it to a square first, as
    :func:`instance_features` does.
    """

    def __init__(
        self,
        model: torch.nn.Module,
        preprocess: Any,
        tokenizer: Any,
        config: Dict[str, Any],
        device: Union[str, torch.device] = "cpu",
        batch_size: int = 32,
    ) -> None:
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        # open_clip's CLIP: encode_image, encode_text and logit_scale are not attributes nn.Module declares
        self.model: Any = model.to(device).eval()
        self.preprocess = preprocess
        self.tokenizer = tokenizer
        self.config = config
        self.device = torch.device(device)
        self.batch_size = batch_size

    @classmethod
    def from_checkpoint(
        cls,
        model_name: str,
        checkpoint_path: Union[str, os.PathLike],
        device: Union[str, torch.device] = "cpu",
        batch_size: int = 32,
    ) -> "ClipEncoder":
        """Load ``model_name`` with weights from a local file; never downloads anything."""
        checkpoint = Path(checkpoint_path).expanduser().resolve()
        if not checkpoint.is_file():
            raise CheckpointNotFoundError(
                f"CLIP checkpoint not found: {checkpoint} (expected the open_clip weights file for {model_name!r}; "
                "download open_clip's pretrained weights on a machine with internet and pass the file's path)"
            )
        _check_open_clip_model_name(model_name)
        import open_clip

        try:
            # An absolute path never matches one of open_clip's pretrained tags, so it loads the file.
            model, _, preprocess = open_clip.create_model_and_transforms(
                model_name, pretrained=str(checkpoint), device="cpu"
            )
        except Exception as error:  # torch.load/load_state_dict raise many types for a wrong file
            # never relay torch's text: for a non-weights file it suggests weights_only=False, unsafe here
            raise ValueError(
                f"{checkpoint} does not hold open_clip weights for {model_name!r} ({load_failure_reason(error, checkpoint)}); "
                "pass the open_clip weights file of that architecture, or the architecture the file was trained with"
            ) from None
        config = {
            "kind": "open_clip",
            "model_name": model_name,
            "checkpoint_sha256": _sha256_of_file(checkpoint),
            "checkpoint_path": str(checkpoint),
        }
        return cls(model, preprocess, open_clip.get_tokenizer(model_name), config, device, batch_size)

    @classmethod
    def random_init(
        cls,
        model_name: str = SMALLEST_OPEN_CLIP_MODEL,
        device: Union[str, torch.device] = "cpu",
        seed: int = 0,
        batch_size: int = 32,
    ) -> "ClipEncoder":
        """Real open_clip model code with seeded random weights, for tests (features mean nothing)."""
        _check_open_clip_model_name(model_name)
        import open_clip

        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            model, _, preprocess = open_clip.create_model_and_transforms(model_name, pretrained=None, device="cpu")
        config = {"kind": "open_clip_random_init", "model_name": model_name, "seed": int(seed)}
        return cls(model, preprocess, open_clip.get_tokenizer(model_name), config, device, batch_size)

    @property
    def logit_scale(self) -> float:
        return float(self.model.logit_scale.exp().item())

    @torch.no_grad()
    def encode_images(self, crops: Sequence[np.ndarray]) -> torch.Tensor:
        from PIL import Image

        if len(crops) == 0:
            raise ValueError("encode_images got no crops; pass at least one HxWx3 uint8 image")
        pil_images = []
        for index, crop in enumerate(crops):
            crop = np.asarray(crop)
            if (
                crop.dtype != np.uint8
                or crop.ndim != 3
                or crop.shape[2] != 3
                or crop.shape[0] == 0
                or crop.shape[1] == 0
            ):
                raise ValueError(
                    f"crop {index} has dtype {crop.dtype} and shape {crop.shape}; expected a non-empty HxWx3 uint8 image"
                )
            pil_images.append(Image.fromarray(np.ascontiguousarray(crop)))
        features = []
        for start in range(0, len(pil_images), self.batch_size):
            batch = torch.stack([self.preprocess(image) for image in pil_images[start : start + self.batch_size]])
            features.append(self.model.encode_image(batch.to(self.device)).float().cpu())
        return F.normalize(torch.cat(features), dim=-1)

    def check_text_length(self, texts: Sequence[str]) -> None:
        """Raise ValueError for a text longer than the model reads (open_clip would silently cut it to 77 tokens)."""
        encode = getattr(self.tokenizer, "encode", None)
        context_length = getattr(self.tokenizer, "context_length", None)
        if encode is None or not context_length or getattr(self.tokenizer, "reduction_fn", None) is not None:
            return
        for text in texts:
            count = len(encode(text))
            if count > context_length - 2:  # start and end tokens take two places
                start = text if len(text) <= 40 else text[:40] + "..."
                raise ValueError(
                    f"the text {start!r} ({len(text)} characters) is {count} tokens long, but CLIP reads at most "
                    f"{context_length - 2} and would silently drop the rest; shorten it"
                )

    @torch.no_grad()
    def encode_text(self, texts: Sequence[str]) -> torch.Tensor:
        if isinstance(texts, str):
            raise ValueError("encode_text takes a list of strings, not a single string; wrap it: [text]")
        if len(texts) == 0 or any(not isinstance(text, str) or not text.strip() for text in texts):
            raise ValueError(f"encode_text needs non-empty strings, got {list(texts)!r}")
        self.check_text_length(texts)
        features = []
        for start in range(0, len(texts), self.batch_size):
            tokens = self.tokenizer(list(texts[start : start + self.batch_size])).to(self.device)
            features.append(self.model.encode_text(tokens).float().cpu())
        return F.normalize(torch.cat(features), dim=-1)


def _encoder_identity(config: Mapping[str, Any]) -> Dict[str, Any]:
    return {key: value for key, value in config.items() if key not in _PROVENANCE_KEYS}


def check_same_encoder(stored: Mapping[str, Any], encoder: EncoderProtocol, what: str = "instance features") -> None:
    """Raise ValueError when ``encoder`` does not produce the feature space ``stored`` describes."""
    stored_identity = _encoder_identity(stored)
    current_identity = _encoder_identity(dict(encoder.config))
    if stored_identity != current_identity:
        keys = sorted(set(stored_identity) | set(current_identity))
        differences = ", ".join(
            f"{key}: {stored_identity.get(key)!r} vs {current_identity.get(key)!r}"
            for key in keys
            if stored_identity.get(key) != current_identity.get(key)
        )
        raise ValueError(
            f"{what} were made with a different encoder ({differences}); recompute them with this encoder "
            "or load the encoder they were made with"
        )
