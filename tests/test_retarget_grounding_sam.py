"""Grounding-DINO + SAM landmark backend with tiny random-weight models (no download, CI-sized).

The models are built from small configs, saved with save_pretrained and loaded back through
grounding_sam.py's own loader (AutoModelForZeroShotObjectDetection / AutoProcessor / SamModel /
SamProcessor from local folders). Random weights give arbitrary boxes and masks, so the test checks
the structure of what comes out (shapes, dtypes, masks inside their boxes, eye order), not quality.
"""

from __future__ import annotations

import numpy as np
import pytest

from t2bs.errors import UserError

transformers = pytest.importorskip("transformers")
torch = pytest.importorskip("torch")

# Every word the processor will tokenize ("eye.", "mouth.") plus BERT's special tokens.
VOCAB = ["[PAD]", "[UNK]", "[CLS]", "[SEP]", "[MASK]", ".", "eye", "mouth", "left", "right"]


def _build_tiny_checkpoints(root):
    """Write a tiny Grounding-DINO folder and a tiny SAM folder (config, weights, processor files)."""
    from transformers import (
        BertConfig,
        BertTokenizer,
        GroundingDinoConfig,
        GroundingDinoForObjectDetection,
        GroundingDinoProcessor,
        SamConfig,
        SamMaskDecoderConfig,
        SamModel,
        SamProcessor,
        SamPromptEncoderConfig,
        SamVisionConfig,
        SwinConfig,
    )
    from transformers.models.grounding_dino.image_processing_pil_grounding_dino import GroundingDinoImageProcessorPil
    from transformers.models.sam.image_processing_pil_sam import SamImageProcessorPil

    torch.manual_seed(0)
    vocab = root / "vocab.txt"
    vocab.write_text("\n".join(VOCAB) + "\n")
    tokenizer = BertTokenizer(str(vocab), do_lower_case=True)
    assert tokenizer("eye.")["input_ids"] == [2, 6, 5, 3]  # [CLS] eye . [SEP]: no [UNK]

    # Swin backbone: 128 px input, 4 px patches, three output stages (strides 8, 16, 32) + one extra
    # level; the deepest map is 2x2, the smallest the detector's GroupNorm accepts.
    swin = SwinConfig(
        image_size=128,
        patch_size=4,
        embed_dim=8,
        depths=[1, 1, 1, 1],
        num_heads=[1, 1, 1, 1],
        window_size=2,
        out_features=["stage2", "stage3", "stage4"],
    )
    bert = BertConfig(
        vocab_size=len(VOCAB),
        hidden_size=32,
        num_hidden_layers=1,
        num_attention_heads=2,
        intermediate_size=32,
        max_position_embeddings=64,
    )
    # d_model must be a multiple of 32 (GroupNorm(32, d_model)); two decoder layers because the box
    # heads of layers > 0 are tied to layer 0's.
    dino_cfg = GroundingDinoConfig(
        backbone_config=swin,
        text_config=bert,
        d_model=32,
        num_queries=10,
        encoder_layers=1,
        decoder_layers=2,
        encoder_ffn_dim=32,
        decoder_ffn_dim=32,
        encoder_attention_heads=2,
        decoder_attention_heads=2,
        max_text_len=32,
        disable_custom_kernels=True,
    )
    dino_dir = root / "grounding-dino"
    GroundingDinoForObjectDetection(dino_cfg).save_pretrained(dino_dir)
    GroundingDinoProcessor(
        image_processor=GroundingDinoImageProcessorPil(size={"shortest_edge": 128, "longest_edge": 128}),
        tokenizer=tokenizer,
    ).save_pretrained(dino_dir)

    sam_cfg = SamConfig(
        vision_config=SamVisionConfig(
            hidden_size=16,
            output_channels=8,
            num_hidden_layers=1,
            num_attention_heads=2,
            image_size=64,
            patch_size=16,
            window_size=2,
            global_attn_indexes=[0],
            num_pos_feats=4,
            mlp_dim=32,
        ),
        prompt_encoder_config=SamPromptEncoderConfig(
            hidden_size=8, image_size=64, patch_size=16, mask_input_channels=4
        ),
        mask_decoder_config=SamMaskDecoderConfig(
            hidden_size=8, mlp_dim=16, num_attention_heads=2, iou_head_hidden_dim=8
        ),
    )
    sam_dir = root / "sam"
    SamModel(sam_cfg).save_pretrained(sam_dir)
    SamProcessor(
        image_processor=SamImageProcessorPil(size={"longest_edge": 64}, pad_size={"height": 64, "width": 64})
    ).save_pretrained(sam_dir)
    return dino_dir, sam_dir


@pytest.fixture(scope="module")
def segmenter(tmp_path_factory):
    from t2bs.face.grounding_sam import GroundingSamSegmenter

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny models: threads only cost time on a shared machine
    try:
        dino_dir, sam_dir = _build_tiny_checkpoints(tmp_path_factory.mktemp("gsam"))
        yield GroundingSamSegmenter.from_pretrained(dino_dir, sam_dir)  # the real loading code
    finally:
        torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def character():
    from t2bs.character.procedural import generate_procedural

    return generate_procedural("a cartoon fox").mesh


def test_tiny_grounding_sam_end_to_end(segmenter, character, mesh_renderer):
    from t2bs.geometry.camera import frontal_camera
    from t2bs.face.landmarks import detect_landmarks

    size = 96
    image = (mesh_renderer.render(character, frontal_camera(size)).rgb * 255).astype(np.uint8)  # [96, 96, 3]
    boxes = segmenter.boxes(image)
    assert set(boxes) <= {"right_eye", "left_eye", "mouth"} and "mouth" in boxes  # top mouth box always exists
    for b in boxes.values():
        assert b.shape == (4,) and 0 <= b[0] <= b[2] <= size - 1 and 0 <= b[1] <= b[3] <= size - 1
    if "left_eye" in boxes:  # eyes sorted by x: the image-left box is the character's right eye
        assert boxes["right_eye"][0] + boxes["right_eye"][2] <= boxes["left_eye"][0] + boxes["left_eye"][2]

    masks = segmenter(image)
    assert set(masks) == {"right_eye", "left_eye", "mouth"}
    for name, m in masks.items():
        assert m.shape == (size, size) and m.dtype == bool
        if name not in boxes:
            assert not m.any()
            continue
        x0, y0, x1, y1 = np.round(boxes[name]).astype(int)
        ys, xs = np.nonzero(m)  # SAM's mask is kept inside its prompt box
        assert ((xs >= x0) & (xs <= x1) & (ys >= y0) & (ys <= y1)).all()

    # Through the landmark detector: 20 landmarks, or (arbitrary masks) the one-line user error.
    try:
        lm, _ = detect_landmarks(character, "grounding-sam", size=size, renderer=mesh_renderer, segmenter=segmenter)
    except UserError as exc:
        assert "Grounding-DINO + SAM found no" in str(exc)
    else:
        assert lm.backend == "grounding-sam" and lm.vertex_ids.shape == (20,)
        assert (lm.vertex_ids >= 0).all() and (lm.vertex_ids < character.num_vertices).all()
