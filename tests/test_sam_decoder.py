"""core/sam_decoder.py gives what segment_anything's MaskDecoder gives for point prompts (multimask outputs)."""

import pytest
import torch
from segment_anything.modeling import MaskDecoder, PromptEncoder, TwoWayTransformer

from votesplat_ns.core.sam_decoder import decode_multimask


def perturbed_decoder(seed: int):
    """SAM's prompt encoder and decoder at its real sizes; every weight moved off its initial value (a LayerNorm
    starts at 1 / 0, which would hide a mistake in how its parameters are applied)."""
    torch.manual_seed(seed)
    prompt_encoder = PromptEncoder(
        embed_dim=256, image_embedding_size=(64, 64), input_image_size=(1024, 1024), mask_in_chans=16
    )
    transformer = TwoWayTransformer(depth=2, embedding_dim=256, mlp_dim=2048, num_heads=8)
    decoder = MaskDecoder(
        num_multimask_outputs=3, transformer=transformer, transformer_dim=256, iou_head_depth=3, iou_head_hidden_dim=256
    )
    with torch.no_grad():
        for parameter in [*decoder.parameters(), *prompt_encoder.parameters()]:
            parameter.add_(0.05 * torch.randn_like(parameter))
    return prompt_encoder.eval(), decoder.eval()


@pytest.mark.parametrize("seed", [0, 1])
def test_shared_and_folded_decoders_give_segment_anythings_outputs(seed, one_torch_thread):
    prompt_encoder, decoder = perturbed_decoder(seed)
    prompts = 6
    points = torch.rand(prompts, 1, 2) * 1024
    with torch.no_grad():
        sparse, dense = prompt_encoder(points=(points, torch.ones(prompts, 1, dtype=torch.int)), boxes=None, masks=None)
        image_pe = prompt_encoder.get_dense_pe()
        embedding = torch.randn(1, 256, 64, 64)
        expected_masks, expected_iou = decoder(
            image_embeddings=embedding,
            image_pe=image_pe,
            sparse_prompt_embeddings=sparse,
            dense_prompt_embeddings=dense,
            multimask_output=True,
        )
        assert expected_masks.shape == (prompts, 3, 256, 256) and expected_iou.shape == (prompts, 3)
        for mode, tolerance in (("shared", 1e-5), ("folded", 1e-4)):
            masks, iou = decode_multimask(decoder, embedding, image_pe, sparse, dense, mode)
            assert masks.shape == expected_masks.shape and iou.shape == expected_iou.shape
            scale = expected_masks.abs().max()
            torch.testing.assert_close(masks, expected_masks, rtol=0, atol=tolerance * scale)
            torch.testing.assert_close(iou, expected_iou, rtol=0, atol=tolerance)
            # the masks themselves (logits above 0) are the same but for a rare pixel within float noise of 0
            flipped = (masks > 0) != (expected_masks > 0)
            assert flipped.float().mean() < 1e-5
            assert (expected_masks[flipped].abs() < tolerance * scale).all()


def test_an_unknown_decoder_is_refused_in_one_line():
    from segment_anything import SamPredictor
    from test_mask_sources import tiny_sam

    from votesplat_ns.core.sam_masks import SamSteps
    from votesplat_ns.errors import VoteSplatInputError

    with pytest.raises(VoteSplatInputError, match="unknown SAM decoder 'fast'; use one of"):
        SamSteps(SamPredictor(tiny_sam()), decoder="fast")
