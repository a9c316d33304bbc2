"""segment_anything's mask decoder over many point prompts of one image, with the image's work done once.

``MaskDecoder.predict_masks`` copies the image embedding and its positional encoding once per prompt
(``repeat_interleave``) and runs the two-way transformer on P copies of 4096 image tokens. Everything the first
block does to the image tokens before they attend to the prompt's tokens is the same for every prompt, and the
attention of the later blocks need not project all 4096 tokens per prompt: a prompt has 7 tokens, so its
projections can be moved onto the tokens instead (``q·(W x + b) = (Wᵀ q)·x + q·b``, and attention rows sum to 1).

:func:`decode_multimask` gives what ``MaskDecoder(..., multimask_output=True)`` gives for point prompts without a
mask input, from segment_anything's own modules and weights:

- ``"shared"``: the modules called as segment_anything calls them, on one copy of the image tokens where the
  first block does not depend on the prompt (torch broadcasts the batch of one);
- ``"folded"``: as ``"shared"``, and the later blocks' image-side projections moved onto the prompt's tokens, so no
  per-prompt tensor of projected image tokens is made.

Both change the order of float reductions, not the maths; ``tests/test_sam_decoder.py`` holds them to
segment_anything's decoder.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Tuple

if TYPE_CHECKING:
    import torch

DECODER_MODES = ("segment_anything", "shared", "folded")
DEFAULT_DECODER = "folded"


def decode_multimask(
    mask_decoder: Any,
    image_embedding: torch.Tensor,  # [1, C, h, w]: one image's encoder output
    image_pe: torch.Tensor,  # [1, C, h, w]: prompt_encoder.get_dense_pe()
    sparse: torch.Tensor,  # [P, T, C]: the prompts' sparse embeddings (points + padding point)
    dense: torch.Tensor,  # [P or 1, C, h, w]: the no-mask embedding, the same for every prompt
    mode: str = "shared",
) -> Tuple[torch.Tensor, torch.Tensor]:
    """Low-resolution mask logits [P, 3, 4h, 4w] and predicted IoUs [P, 3] of the three multimask outputs."""
    import torch

    if mode not in DECODER_MODES:
        raise ValueError(f"decoder mode '{mode}' is not one of {DECODER_MODES}")
    if mode == "segment_anything":
        return mask_decoder(
            image_embeddings=image_embedding,
            image_pe=image_pe,
            sparse_prompt_embeddings=sparse,
            dense_prompt_embeddings=dense,
            multimask_output=True,
        )
    dec = mask_decoder
    output_tokens = torch.cat([dec.iou_token.weight, dec.mask_tokens.weight], dim=0)
    tokens = torch.cat((output_tokens.unsqueeze(0).expand(sparse.size(0), -1, -1), sparse), dim=1)
    # the no-mask embedding is one vector broadcast over the image: one copy serves every prompt
    src = image_embedding + dense[:1]
    _, c, h, w = src.shape
    hs, keys = _two_way_transformer(dec.transformer, src, image_pe, tokens, folded=mode == "folded")
    iou_token_out = hs[:, 0, :]
    mask_tokens_out = hs[:, 1 : 1 + dec.num_mask_tokens, :]
    # only the three multimask outputs are returned: the single-mask token's hypernetwork is not needed
    hyper_in = torch.stack([dec.output_hypernetworks_mlps[i](mask_tokens_out[:, i, :]) for i in (1, 2, 3)], dim=1)
    if mode == "folded":
        masks = _upscaled_masks(dec.output_upscaling, keys, hyper_in, h, w)
    else:
        upscaled = dec.output_upscaling(keys.transpose(1, 2).view(keys.shape[0], c, h, w))
        bu, cu, hu, wu = upscaled.shape
        masks = (hyper_in @ upscaled.view(bu, cu, hu * wu)).view(bu, -1, hu, wu)
    iou_pred = dec.iou_prediction_head(iou_token_out)[:, 1:]
    return masks, iou_pred


# prompts per chunk of the token-major upscaling: its two per-prompt tensors take 12 MiB a prompt in float32
UPSCALING_PROMPTS_PER_CHUNK = 64


def _upscaled_masks(
    upscaling: Any,  # segment_anything's output_upscaling: ConvT(2, 2) -> LayerNorm2d -> GELU -> ConvT(2, 2) -> GELU
    keys: torch.Tensor,  # [P, h·w, C]: the image tokens after the transformer, row-major
    hyper_in: torch.Tensor,  # [P, M, C/8]: the mask tokens' hypernetwork outputs
    h: int,
    w: int,
) -> torch.Tensor:
    """``hyper_in @ output_upscaling(keys)`` as [P, M, 4h, 4w], computed token by token.

    A transposed convolution with kernel 2 and stride 2 maps each input pixel to its own 2×2 output pixels, and
    the LayerNorm and GELU act per pixel, so the whole upscaling is a function of one image token: two matrix
    products over the tokens ([P·h·w, C] → 4 sub-pixels × C/4 → 16 sub-pixels × C/8), the channel LayerNorm over
    contiguous rows (``F.layer_norm``, one pass instead of LayerNorm2d's eight strided ones) and the GELUs. The
    pixels are put in image order only for the M masks. Float sums run in another order than the
    convolutions', and in float32 rather than cuDNN's default TF32 on a GPU.
    """
    import torch
    import torch.nn.functional as F

    conv1, norm, act1, conv2, act2 = upscaling
    if not (
        isinstance(conv1, torch.nn.ConvTranspose2d)
        and isinstance(conv2, torch.nn.ConvTranspose2d)
        and conv1.kernel_size == conv1.stride == conv2.kernel_size == conv2.stride == (2, 2)
        and isinstance(act1, torch.nn.GELU)
        and isinstance(act2, torch.nn.GELU)
    ):
        raise ValueError("the token-major upscaling needs segment_anything's output_upscaling layers")
    assert conv1.bias is not None and conv2.bias is not None  # segment_anything's layers have biases
    prompts, tokens, channels = keys.shape
    c1, c2 = conv1.out_channels, conv2.out_channels
    # [C_in, C_out, a, b] -> [C_in, (a, b, C_out)]: each sub-pixel's channels contiguous
    w1 = conv1.weight.permute(0, 2, 3, 1).reshape(channels, 4 * c1)
    b1 = conv1.bias.repeat(4)
    w2 = conv2.weight.permute(0, 2, 3, 1).reshape(c1, 4 * c2)
    b2 = conv2.bias.repeat(4)
    masks = hyper_in.shape[1]
    out = []
    for start in range(0, prompts, UPSCALING_PROMPTS_PER_CHUNK):
        chunk = keys[start : start + UPSCALING_PROMPTS_PER_CHUNK]
        p = chunk.shape[0]
        x = torch.addmm(b1, chunk.reshape(p * tokens, channels), w1).view(p * tokens * 4, c1)
        x = act1(F.layer_norm(x, (c1,), norm.weight, norm.bias, norm.eps))
        x = act2(torch.addmm(b2, x, w2))  # [(P, h·w, a, b), (a2, b2, C/8)]
        m = x.view(p, tokens * 16, c2) @ hyper_in[start : start + p].transpose(1, 2)  # [P, (i, j, a, b, a2, b2), M]
        m = m.view(p, h, w, 2, 2, 2, 2, masks).permute(0, 7, 1, 3, 5, 2, 4, 6)  # [P, M, i, a, a2, j, b, b2]
        out.append(m.reshape(p, masks, 4 * h, 4 * w))
    return torch.cat(out) if len(out) > 1 else out[0]


def _two_way_transformer(
    transformer: Any, src: torch.Tensor, image_pe: torch.Tensor, tokens: torch.Tensor, folded: bool
):
    """``TwoWayTransformer.forward`` with the image tokens kept as one copy [1, N, C] until a block makes them
    depend on the prompt ([P, N, C] after the first block's image-to-token attention)."""
    keys = src.flatten(2).permute(0, 2, 1)  # [1, N, C]
    key_pe = image_pe.flatten(2).permute(0, 2, 1)
    query_pe = tokens
    queries = tokens
    for layer in transformer.layers:
        if layer.skip_first_layer_pe:
            queries = layer.self_attn(q=queries, k=queries, v=queries)
        else:
            q = queries + query_pe
            queries = queries + layer.self_attn(q=q, k=q, v=queries)
        queries = layer.norm1(queries)
        q = queries + query_pe
        k = keys + key_pe
        queries = layer.norm2(queries + _token_to_image(layer.cross_attn_token_to_image, q, k, keys, folded))
        queries = layer.norm3(queries + layer.mlp(queries))
        q = queries + query_pe
        if folded:
            attn_out = _image_to_token_folded(layer.cross_attn_image_to_token, k, q, queries)
        else:
            attn_out = layer.cross_attn_image_to_token(q=k, k=q, v=queries)
        keys = layer.norm4(keys + attn_out)
    q = queries + query_pe
    k = keys + key_pe
    queries = transformer.norm_final_attn(
        queries + _token_to_image(transformer.final_attn_token_to_image, q, k, keys, folded)
    )
    return queries, keys


def _token_to_image(attn: Any, q: torch.Tensor, k: torch.Tensor, keys: torch.Tensor, folded: bool) -> torch.Tensor:
    """The prompt's tokens attending to the image tokens; folded only where the image tokens are per prompt (one
    shared copy is projected once either way)."""
    if folded and keys.shape[0] > 1:
        return _token_to_image_folded(attn, q, k, keys)
    return attn(q=q, k=k, v=keys)


def _heads_of(weight: torch.Tensor, num_heads: int) -> torch.Tensor:
    """A projection's weight [c, C] as [H, d, C] (head h: rows h·d … h·d + d - 1, as ``_separate_heads``)."""
    c, embedding = weight.shape
    return weight.reshape(num_heads, c // num_heads, embedding)


def _token_to_image_folded(attn: Any, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``Attention.forward(q, k, v)`` with T queries (the prompt's tokens) and N keys (image tokens), without
    projecting the N keys and values: the key projection moves onto the queries (its bias adds the same to every
    key's score, which the softmax removes) and the value projection after the weighted sum (weights sum to 1)."""
    import torch

    p, t, _ = q.shape
    heads = attn.num_heads
    qp = attn.q_proj(q).reshape(p, t, heads, -1).transpose(1, 2)  # [P, H, T, d]
    d = qp.shape[-1]
    w_k = _heads_of(attn.k_proj.weight, heads)  # [H, d, C]
    g = torch.einsum("phtd,hdc->phtc", qp, w_k).reshape(p, heads * t, -1)  # [P, H·T, C]
    scores = (g @ k.transpose(1, 2)) / math.sqrt(d)  # [P, H·T, N]
    weights = torch.softmax(scores, dim=-1)
    summed = (weights @ v).reshape(p, heads, t, -1)  # [P, H, T, C]
    w_v = _heads_of(attn.v_proj.weight, heads)
    out = torch.einsum("phtc,hdc->phtd", summed, w_v) + attn.v_proj.bias.reshape(heads, 1, d)
    return attn.out_proj(out.transpose(1, 2).reshape(p, t, heads * d))


def _image_to_token_folded(attn: Any, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``Attention.forward(q, k, v)`` with N queries (image tokens, [1 or P, N, C]) and T keys (the prompt's tokens):
    the query projection moves onto the keys and the output projection onto the values, so the only per-prompt
    products over the N image tokens have H·T columns."""
    import torch

    p, t, _ = k.shape
    heads = attn.num_heads
    kp = attn.k_proj(k).reshape(p, t, heads, -1).transpose(1, 2)  # [P, H, T, d]
    vp = attn.v_proj(v).reshape(p, t, heads, -1).transpose(1, 2)
    d = kp.shape[-1]
    w_q = _heads_of(attn.q_proj.weight, heads)  # [H, d, C]
    m = torch.einsum("hdc,phtd->pcht", w_q, kp).reshape(p, -1, heads * t)  # [P, C, H·T]
    bias = torch.einsum("hd,phtd->pht", attn.q_proj.bias.reshape(heads, d), kp).reshape(p, 1, heads * t)
    scores = ((q @ m + bias) / math.sqrt(d)).reshape(p, -1, heads, t)  # [P, N, H, T]
    weights = torch.softmax(scores, dim=-1).reshape(p, -1, heads * t)
    w_o = attn.out_proj.weight.reshape(-1, heads, d)  # [C, H, d]: out_proj's input columns by head
    r = torch.einsum("phtd,chd->phtc", vp, w_o).reshape(p, heads * t, -1)  # [P, H·T, C]
    return weights @ r + attn.out_proj.bias
