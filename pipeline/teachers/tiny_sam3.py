"""A tiny, randomly initialised SAM 3 checkpoint for offline tests and the teacher benchmark.

transformers' test config and a tokenizer written here; ``size="real"`` builds the full architecture for GPU
timing.  A test model, no teacher: its answers are random (or, fitted, those of :func:`box_scenes`).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline.teachers.sam3 import TEXT_MAX_LENGTH, Sam3Teacher

__all__ = ["write_clip_vocab", "tiny_sam3_config", "preprocessor_config", "build_tiny_sam3", "box_scenes",
           "FIT_IMAGE_SIZE", "FIT_STEPS", "FIT_BATCH", "FIT_LR", "FIT_SCORE_TARGET", "fit_tiny_sam3"]


def write_clip_vocab(directory: str | Path, words: tuple[str, ...] = ()) -> tuple[Path, Path]:
    """Write a minimal CLIP BPE vocabulary (``vocab.json`` + ``merges.txt``).

    It holds the byte symbols, with and without ``</w>``, the two special tokens, and whole-word merges for
    ``words``.

    Parameters
    ----------
    directory : str or Path
        Where both files are written (created if missing; existing files of those names are replaced).
    words : tuple of str, optional
        Words that become single tokens.

    Returns
    -------
    tuple of Path
        The ``vocab.json`` and ``merges.txt`` paths.
    """
    from transformers.convert_slow_tokenizer import bytes_to_unicode  # GPT-2 / CLIP byte-level alphabet

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    symbols = list(bytes_to_unicode().values())
    vocab: dict[str, int] = {"<|startoftext|>": 0, "<|endoftext|>": 1}  # ids the text config names
    for s in symbols + [s + "</w>" for s in symbols]:
        vocab.setdefault(s, len(vocab))
    merges: list[str] = []
    for word in words:
        pieces = list(word)
        if not pieces:
            continue
        pieces[-1] += "</w>"
        while len(pieces) > 1:
            a, b = pieces[0], pieces[1]
            merges.append(f"{a} {b}")
            vocab.setdefault(a + b, len(vocab))
            pieces = [a + b] + pieces[2:]
    vpath, mpath = directory / "vocab.json", directory / "merges.txt"
    vpath.write_text(json.dumps(vocab))
    mpath.write_text("#version: 0.2\n" + "\n".join(dict.fromkeys(merges)) + "\n")
    return vpath, mpath


def tiny_sam3_config(image_size: int = 56, num_queries: int = 5, initializer_range: float = 0.2):
    """Build the small Sam3Config of transformers' SAM 3 tests (image 56 = 4 x 14 patches).

    Parameters
    ----------
    image_size : int, optional
        Input side in pixels (14-pixel patches; attention windows of half the patch grid's side).
    num_queries : int, optional
        DETR decoder queries.
    initializer_range : float, optional
        The weights' initial spread in every sub-config; the default is 10x transformers', so the random
        model's answers depend visibly on the image and the prompt.

    Returns
    -------
    transformers.Sam3Config
        The config.
    """
    from transformers.models.sam3.configuration_sam3 import (
        Sam3Config, Sam3DETRDecoderConfig, Sam3DETREncoderConfig, Sam3GeometryEncoderConfig,
        Sam3MaskDecoderConfig, Sam3VisionConfig, Sam3ViTConfig)

    backbone = Sam3ViTConfig(hidden_size=32, num_hidden_layers=2, num_attention_heads=4, intermediate_size=64,
                             num_channels=3, image_size=image_size, patch_size=14,
                             window_size=image_size // 14 // 2, global_attn_indexes=[0, 1])
    vision = Sam3VisionConfig(backbone_config=backbone, fpn_hidden_size=32, scale_factors=[2.0, 1.0])
    text = {"vocab_size": 1000, "hidden_size": 32, "intermediate_size": 64, "projection_dim": 32,
            "num_hidden_layers": 2, "num_attention_heads": 4, "max_position_embeddings": 32, "hidden_act": "gelu",
            "bos_token_id": 0, "eos_token_id": 1, "pad_token_id": 1}
    config = Sam3Config(
        vision_config=vision, text_config=text,
        geometry_encoder_config=Sam3GeometryEncoderConfig(hidden_size=32, num_layers=1, num_attention_heads=4,
                                                          intermediate_size=64, mask_fuser_hidden_size=32,
                                                          mask_fuser_num_layers=1),
        detr_encoder_config=Sam3DETREncoderConfig(hidden_size=32, num_layers=1, num_attention_heads=4,
                                                  intermediate_size=64),
        detr_decoder_config=Sam3DETRDecoderConfig(hidden_size=32, num_layers=1, num_queries=num_queries,
                                                  num_attention_heads=4, intermediate_size=64),
        mask_decoder_config=Sam3MaskDecoderConfig(hidden_size=32, num_upsampling_stages=2),
    )
    config.initializer_range = initializer_range
    for sub in (backbone, vision, config.text_config, config.geometry_encoder_config, config.detr_encoder_config,
                config.detr_decoder_config, config.mask_decoder_config):
        if hasattr(sub, "initializer_range"):
            sub.initializer_range = initializer_range
    return config


def preprocessor_config(image_size: int) -> dict:
    """Write out the image-processor settings SAM 3 checkpoints ship (resize to a square, rescale, normalise).

    Parameters
    ----------
    image_size : int
        Side of the square the images are resized to.

    Returns
    -------
    dict
        The contents of ``preprocessor_config.json``.
    """
    return {"image_processor_type": "Sam3ImageProcessor", "do_resize": True,
            "size": {"height": image_size, "width": image_size}, "resample": 2,
            "do_rescale": True, "rescale_factor": 1 / 255, "do_normalize": True,
            "image_mean": [0.5, 0.5, 0.5], "image_std": [0.5, 0.5, 0.5], "do_convert_rgb": True}


def build_tiny_sam3(directory: str | Path, *, image_size: int = 56, seed: int = 0,  # not a param: init seed
                    size: str = "tiny",
                    words: tuple[str, ...] = (), initializer_range: float = 0.2) -> Path:
    """Save a randomly initialised SAM 3 with tokenizer and processor config.

    Parameters
    ----------
    directory : str or Path
        Where the checkpoint is written (created if missing; its files are replaced).
    image_size : int, optional
        The tiny model's input side (:func:`tiny_sam3_config`); the real model keeps its own.
    seed : int, optional
        Torch seed of the random weights.
    size : str, optional
        ``tiny`` (:func:`tiny_sam3_config`) or ``real`` (transformers' default Sam3Config, for GPU timing).
    words : tuple of str, optional
        Words the tokenizer holds as single tokens (:func:`write_clip_vocab`).
    initializer_range : float, optional
        The tiny model's initial weight spread (:func:`tiny_sam3_config`).

    Returns
    -------
    Path
        ``directory``.

    Raises
    ------
    ValueError
        ``size`` is neither ``tiny`` nor ``real``.
    """
    import torch
    from transformers import CLIPTokenizer, Sam3Config, Sam3Model

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(seed)
    if size == "tiny":
        config = tiny_sam3_config(image_size, initializer_range=initializer_range)
    elif size == "real":
        config = Sam3Config()
        image_size = config.vision_config.backbone_config.image_size
    else:
        raise ValueError(f"size {size!r}: expected tiny or real")
    model = Sam3Model(config).eval()
    model.save_pretrained(directory)
    vpath, mpath = write_clip_vocab(directory, words)
    merges = [tuple(line.split()) for line in mpath.read_text().splitlines()[1:] if line.strip()]
    tok = CLIPTokenizer(vocab=json.loads(vpath.read_text()), merges=merges)
    tok.save_pretrained(directory)
    (directory / "preprocessor_config.json").write_text(json.dumps(preprocessor_config(image_size), indent=1))
    return directory


def box_scenes(rng, n: int, size: int = 40):
    """Synthetic scenes for the fitted tiny SAM 3: one bright box on a dark, noisy background.

    Parameters
    ----------
    rng : numpy.random.Generator
        The draws (box corner, box size, colour, noise).
    n : int
        Number of scenes.
    size : int
        Side of each square scene in pixels (the box is 8--13 pixels a side, at least 5 from the top left).

    Returns
    -------
    list of (numpy.ndarray, numpy.ndarray)
        ``(image uint8 [size, size, 3], box mask bool [size, size])`` per scene.
    """
    scenes = []
    for _ in range(n):
        img = np.full((size, size, 3), 15, np.uint8)
        y, x = rng.integers(5, size - 15, size=2)
        h, w = rng.integers(8, 14, size=2)
        img[y:y + h, x:x + w] = rng.integers(120, 255, size=3)
        mask = np.zeros((size, size), bool)
        mask[y:y + h, x:x + w] = True
        scenes.append((img + rng.integers(0, 20, img.shape, dtype=np.uint8), mask))
    return scenes


#: the fitted tiny SAM 3's recipe: input side (16 x 16 mask logits, a cell of 2.5 px on a 40 px scene), Adam
#: steps, images per step, learning rate, and the detection / presence target (0.9, so scores stay off the
#: sigmoid's flat end and their difference still measures the arithmetic)
FIT_IMAGE_SIZE, FIT_STEPS, FIT_BATCH, FIT_LR, FIT_SCORE_TARGET = 112, 300, 8, 3e-3, 0.9


def fit_tiny_sam3(directory: str | Path, prompts: tuple[str, ...], *, seed: int = 0,  # not a param: fit seed
                  steps: int = FIT_STEPS,
                  scene_size: int = 40) -> Path:
    """Build a tiny SAM 3 and fit it to :func:`box_scenes`, so that its mask logits have a trained model's margins.

    A random tiny SAM 3 amplifies any rounding (its mask logits sit near the threshold over whole cells), so a
    bf16-vs-fp32 mask IoU measured on it says more about the random weights than about the arithmetic; this
    model answers "the box" confidently for every prompt, as a trained teacher answers its object. It tests
    numerics only: it is no teacher. Every query's mask logits, upsampled to the scene, are fitted to the box
    by binary cross-entropy, and the detection and presence logits to :data:`FIT_SCORE_TARGET`; fp32, Adam,
    :data:`FIT_BATCH` scenes and one prompt each per step (about 12 s on two cores).

    Parameters
    ----------
    directory : str or Path
        Where the checkpoint is written (as :func:`build_tiny_sam3` writes it).
    prompts : tuple of str
        The prompts it is fitted under; their words make its vocabulary.
    seed : int
        Seed of the initial weights and of the scenes and prompts drawn.
    steps : int
        Adam steps.
    scene_size : int
        Side of the training scenes in pixels.

    Returns
    -------
    Path
        ``directory``.
    """
    import torch
    import torch.nn.functional as F
    from transformers import AutoTokenizer, Sam3Model

    words = tuple(dict.fromkeys(w for p in prompts for w in p.split()))
    directory = build_tiny_sam3(directory, image_size=FIT_IMAGE_SIZE, seed=seed, words=words)
    model = Sam3Model.from_pretrained(directory, local_files_only=True).train()
    tok = AutoTokenizer.from_pretrained(directory, local_files_only=True)(
        list(prompts), padding="max_length", max_length=TEXT_MAX_LENGTH, truncation=True, return_tensors="pt")
    preprocess = Sam3Teacher(directory, device="cpu", dtype="fp32").preprocess
    rng = np.random.default_rng(seed)
    scenes = box_scenes(rng, 64, scene_size)
    opt = torch.optim.Adam(model.parameters(), lr=FIT_LR)
    for _ in range(steps):
        pick = rng.integers(0, len(scenes), FIT_BATCH)
        k = torch.from_numpy(rng.integers(0, len(prompts), FIT_BATCH))
        boxes = torch.from_numpy(np.stack([scenes[i][1] for i in pick])).float()[:, None]
        out = model(pixel_values=preprocess([scenes[i][0] for i in pick]), input_ids=tok["input_ids"][k],
                    attention_mask=tok["attention_mask"][k])
        logits = F.interpolate(out.pred_masks, size=(scene_size, scene_size), mode="bilinear", align_corners=False)
        loss = F.binary_cross_entropy_with_logits(logits, boxes.expand_as(logits))
        for score in (out.pred_logits, out.presence_logits):
            if score is not None:
                loss = loss + F.binary_cross_entropy_with_logits(score, torch.full_like(score, FIT_SCORE_TARGET))
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval().save_pretrained(directory)
    return directory
