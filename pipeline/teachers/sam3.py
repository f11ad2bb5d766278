r"""SAM 3 text-prompt teacher through transformers (>= 5), from a local ``save_pretrained`` directory only.

eq:teacher-prediction: a query's score is :math:`\sigma(\ell_q)\,\sigma(\ell_{presence})`; the answer is
the best query's mask and score, invalid when no query is above ``teacher.score_threshold``.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import inspect
import json
import logging
import math
import types
from pathlib import Path
from typing import Sequence

import numpy as np
from fsspec.core import url_to_fs
from fsspec.implementations.local import LocalFileSystem

from pipeline.artifacts.atomic import read_json, write_json
from pipeline.params import PAPER
from pipeline.runtime.device import resolve_device, reuse_freed_memory, teacher_cpu_dtype
from pipeline.runtime.errors import InputError, Option, literal
from pipeline.teacher_table import SAM3 as BACKEND
from pipeline.runtime.progress import library_bars_off
from pipeline.teachers import attention
from pipeline.teachers.attention import OpenVINOAttention, attention_engine, resolve_teacher_engine
from pipeline.teachers.base import RegisteredTeacher, TeacherInput, files_digest, finalize_answers

__all__ = ["TEXT_MAX_LENGTH", "SAM3_MODEL_TYPES", "checkpoint_hash", "checkpoint_stat", "memoised_checkpoint_hash",
           "read_processor_config", "check_checkpoint_dir", "resolve_teacher_dtype", "allow_tf32", "MAX_AUTO_BATCH",
           "auto_batch_size", "local_hash_memo", "first_self_attention_once_per_image", "SAM3_PATCHES",
           "upstream_source_digest", "upstream_matches", "exact_savings", "ONEDNN_PATH", "FUSED_MLP_TARGET",
           "onednn_post_op", "fused_mlp_activations", "Sam3Teacher"]

log = logging.getLogger(__name__)

#: tokens per prompt: Sam3Processor pads prompts to 32 tokens
TEXT_MAX_LENGTH = 32
#: ``model_type`` values of a checkpoint's config.json that :func:`check_checkpoint_dir` accepts
SAM3_MODEL_TYPES = ("sam3", "sam3_video")
_WEIGHT_SUFFIXES = (".safetensors", ".bin", ".pt", ".pth")


def checkpoint_hash(directory: Path) -> str:
    """Hash the checkpoint's files: sha256 over name and bytes, sorted (weights, configs and tokenizer).

    Parameters
    ----------
    directory : Path
        The checkpoint directory; hidden files are left out.

    Returns
    -------
    str
        The hex sha256 (:func:`pipeline.teachers.base.files_digest`).
    """
    return files_digest(directory, _checkpoint_files(directory))


def _checkpoint_files(directory: Path) -> list[Path]:
    """List the checkpoint's files, at any depth and sorted; hidden files are left out."""
    return sorted(q for q in directory.rglob("*") if q.is_file() and not q.name.startswith("."))


def checkpoint_stat(directory: Path) -> list[list]:
    """Stat every checkpoint file: what the hash memo is keyed on.

    Parameters
    ----------
    directory : Path
        The checkpoint directory.

    Returns
    -------
    list of list
        ``[relative path, size, mtime_ns]`` per file, sorted by path.
    """
    return [[str(p.relative_to(directory)), int((st := p.stat()).st_size), int(st.st_mtime_ns)]
            for p in _checkpoint_files(directory)]


def memoised_checkpoint_hash(directory: Path, memo: Path | None) -> str:
    """Hash the checkpoint once: :func:`checkpoint_hash`, remembered while no file's size or mtime changes.

    An unreadable memo is recomputed (and rewritten, atomically).

    Parameters
    ----------
    directory : Path
        The checkpoint directory.
    memo : Path or None
        The JSON file of remembered hashes, keyed by the resolved directory and its :func:`checkpoint_stat`;
        None: always hash.

    Returns
    -------
    str
        The hex sha256 of the checkpoint.
    """
    if memo is None:
        return checkpoint_hash(directory)
    memo = Path(memo)
    key, stat, table = str(Path(directory).resolve()), checkpoint_stat(directory), read_json(memo)
    entry = table.get(key)
    if isinstance(entry, dict) and entry.get("files") == stat and isinstance(entry.get("sha256"), str):
        return entry["sha256"]
    digest = checkpoint_hash(directory)
    table[key] = {"files": stat, "sha256": digest}
    write_json(memo, table)
    return digest


def read_processor_config(directory: Path) -> dict:
    """Read the image-processor settings from ``preprocessor_config.json`` or ``processor_config.json``.

    Parameters
    ----------
    directory : Path
        The checkpoint directory; the first of the two files found is read.

    Returns
    -------
    dict
        The settings (a ``processor_config.json``'s ``image_processor`` section where it has one).

    Raises
    ------
    InputError
        The file found is not valid JSON, or neither file exists (naming the file or directory).
    """
    for name in ("preprocessor_config.json", "processor_config.json"):
        p = directory / name
        if p.exists():
            try:
                cfg = json.loads(p.read_text())
            except json.JSONDecodeError:
                raise InputError(f"{p}: not valid JSON") from None
            return cfg["image_processor"] if isinstance(cfg.get("image_processor"), dict) else cfg
    raise InputError(f"{directory}: no preprocessor_config.json / processor_config.json "
                     "(save the Sam3Processor with the model)")


def check_checkpoint_dir(directory: str | Path, option: Option | None = None) -> Path:
    """Check that ``directory`` is a local SAM 3 checkpoint: config, weights and CLIP tokenizer files.

    Parameters
    ----------
    directory : str or Path
        The checkpoint directory (``~`` expanded); nothing is downloaded.
    option : Option or None, optional
        The user option that named it, for the error line; None: the params key ``teacher.checkpoint``.

    Returns
    -------
    Path
        The directory.

    Raises
    ------
    InputError
        It is not a directory, has no (valid JSON) config.json, its ``model_type`` is not in
        :data:`SAM3_MODEL_TYPES`, or it lacks weights or tokenizer files (one line saying which).
    """
    d = Path(directory).expanduser()

    def refuse(where: Path | None, why: str) -> InputError:  # where: a file in it (None: the folder itself)
        """Build the error naming ``where`` (or the folder, or the option) and ``why``."""
        if option is None:
            return InputError(f"{where or d}: {why}" if where is not None or d.is_dir() else
                              f"teacher.checkpoint={str(directory)!r}: {why}")
        return InputError("{}: " + literal(f"{where}: {why}" if where is not None else why), option(directory))

    if not d.is_dir():
        raise refuse(None, "directory not found (a local SAM 3 checkpoint saved with save_pretrained; "
                           "nothing is downloaded)")
    cfg_path = d / "config.json"
    if not cfg_path.exists():
        raise refuse(None, "not a SAM 3 checkpoint (no config.json)")
    try:
        model_type = json.loads(cfg_path.read_text()).get("model_type")
    except json.JSONDecodeError:
        raise refuse(cfg_path, "not valid JSON") from None
    if model_type not in SAM3_MODEL_TYPES:
        raise refuse(None, f"not a SAM 3 checkpoint (config.json model_type={model_type!r}, expected 'sam3')")
    if not any(p.suffix in _WEIGHT_SUFFIXES for p in d.iterdir()):
        raise refuse(None, "SAM 3 checkpoint without weights (*.safetensors)")
    if not any((d / f).exists() for f in ("tokenizer.json", "vocab.json")):
        raise refuse(None, "SAM 3 checkpoint without CLIP tokenizer files (tokenizer.json or vocab.json)")
    return d


def resolve_teacher_dtype(dtype: str, device) -> tuple[str, bool]:
    """Resolve ``teacher.dtype`` on ``device`` to the weights' dtype and whether TF32 is on.

    ``auto`` is bf16 on a CUDA GPU that supports it, else fp32 with TF32 on CUDA; on a CPU the rule on its flags,
    :func:`pipeline.runtime.device.teacher_cpu_dtype` (bf16 with AMX, or avx512_bf16 on AMD, else fp32).

    Parameters
    ----------
    dtype : str
        ``auto``, ``fp32`` or ``bf16``; a pinned dtype is kept, TF32 off.
    device : str or torch.device
        The device the teacher runs on.

    Returns
    -------
    tuple of (str, bool)
        (``"fp32"`` or ``"bf16"``, TF32 on).

    Raises
    ------
    InputError
        ``dtype`` is none of the three.
    """
    import torch

    if dtype not in ("auto", "fp32", "bf16"):
        raise InputError(f"teacher.dtype={dtype!r}: expected auto, fp32 or bf16")
    if dtype != "auto":
        return dtype, False
    if torch.device(device).type != "cuda":
        return teacher_cpu_dtype(), False
    return ("bf16", False) if torch.cuda.is_bf16_supported() else ("fp32", True)


@contextlib.contextmanager
def allow_tf32(on: bool):
    """Allow TF32 matmuls and cuDNN convolutions inside the context (restored after); a no-op when off.

    Parameters
    ----------
    on : bool
        Whether to turn TF32 on.

    Yields
    ------
    None
    """
    import torch

    old = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    if on:
        torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = old


#: at most this many images per forward: a larger batch only delays the first answers
MAX_AUTO_BATCH = 16


def auto_batch_size(device, used_bytes: int | None = None, free_bytes: int | None = None,
                    headroom: float = 0.7) -> int:
    """Size the images per forward to fill ``headroom`` of the free GPU memory.

    The per-image cost is the peak memory of one image's forward above the model (``used_bytes``):
    ``min(MAX_AUTO_BATCH, max(1, headroom * free_bytes // used_bytes))``.

    Parameters
    ----------
    device : str or torch.device
        The device; on a CPU (with either figure not given) the answer is 2.
    used_bytes : int or None, optional
        One image's forward's peak memory above the model; None: measured by torch's peak-memory counters
        (reset before that forward).
    free_bytes : int or None, optional
        Free device memory; None: asked of the GPU.
    headroom : float, optional
        Fraction of the free memory to fill.

    Returns
    -------
    int
        Images per forward, in [1, :data:`MAX_AUTO_BATCH`].
    """
    import torch

    if torch.device(device).type != "cuda" and (used_bytes is None or free_bytes is None):
        return 2
    if used_bytes is None:
        used_bytes = torch.cuda.max_memory_allocated(device) - torch.cuda.memory_allocated(device)
    if free_bytes is None:
        free_bytes = torch.cuda.mem_get_info(device)[0]
    per_image = max(int(used_bytes), 1)
    return int(min(MAX_AUTO_BATCH, max(1, (headroom * free_bytes) // per_image)))


def local_hash_memo(cache_dir: str) -> Path | None:
    """Place the checkpoint-hash memo beside a local teacher cache.

    Parameters
    ----------
    cache_dir : str
        ``teacher.cache_dir``: a local path or an fsspec URL.

    Returns
    -------
    Path or None
        ``<cache_dir>/checkpoint_hashes.json``; None for object storage (the hash is computed each run).
    """
    fs, path = url_to_fs(str(cache_dir))
    return Path(path) / "checkpoint_hashes.json" if isinstance(fs, LocalFileSystem) else None


@contextlib.contextmanager
def first_self_attention_once_per_image(model, copies: int):
    """Run the DETR encoder's first self-attention once per image instead of once per (image, prompt).

    Its input is the image's features and position encoding only (the prompt enters at the cross-attention that
    follows), and :meth:`Sam3Teacher.heads` repeats each image's features ``copies`` times image-major, so rows
    ``b * copies ... (b + 1) * copies - 1`` of its query, key and value are equal: computing row ``b * copies``
    and repeating it gives the same answer for (copies - 1) / copies less of that layer's attention (about 1-2 s
    of 25 s per image for six prompts, real size, 2 avx512_bf16 cores). Any other call (an attention mask, a
    batch that ``copies`` does not divide) runs unchanged, as does a model whose encoder is laid out otherwise.

    Parameters
    ----------
    model : transformers.Sam3Model
        The loaded model; its first DETR encoder layer's ``self_attn`` is wrapped inside the context only.
    copies : int
        Prompts per image: consecutive rows of the batch that hold the same image.

    Yields
    ------
    None
    """
    layers = getattr(getattr(model, "detr_encoder", None), "layers", None)
    attn = getattr(layers[0], "self_attn", None) if layers else None
    if copies < 2 or attn is None:
        yield
        return
    forward = attn.forward

    def once_per_image(query, key, value, attention_mask=None, **kwargs):
        """Attend over row ``b * copies`` of each image and repeat it; any other call runs unchanged."""
        if attention_mask is not None or query.shape[0] % copies:
            return forward(query, key, value, attention_mask=attention_mask, **kwargs)
        out, _ = forward(query[::copies], key[::copies], value[::copies], **kwargs)
        return out.repeat_interleave(copies, dim=0), None

    attn.forward = once_per_image  # an instance attribute: nn.Module.__call__ reads self.forward
    try:
        yield
    finally:
        del attn.forward


def _rope_fewer_passes(q, k, cos, sin):
    """Apply transformers' ``apply_rotary_pos_emb_2d`` with the same arithmetic in fewer memory passes.

    The pairwise rotation times ``sin``, ``rotate_pairwise(x) * sin``, equals ``swap_pairs(x) * sin_signed`` bit
    for bit (negation is exact), so the negated half and the stacked copy become one swapped copy, and the sum is
    taken in place; the fp32 round trip of a bf16 input stays (its rounding is the model's). Where
    :func:`_complex_rotation_is_exact`, the rotation is one complex product instead (the same bits, a third of the
    time).
    """
    import torch

    if k.shape == q.shape and _complex_rotation_is_exact(q, cos, sin, torch.get_num_threads()):
        rotation = torch.complex(cos[..., 0::2].float(), sin[..., 0::2].float())

        def rotate(x):
            """Rotate ``x`` as complex pairs in fp32 (a copy, in ``x``'s layout) and cast back to its dtype."""
            xf = x.to(torch.float32, copy=True)
            torch.view_as_complex(xf.unflatten(-1, (-1, 2))).mul_(rotation)
            return xf.type_as(x)

        return rotate(q), rotate(k)

    sin_signed = (sin.unflatten(-1, (-1, 2)) * torch.tensor([-1.0, 1.0], dtype=sin.dtype, device=sin.device)
                  ).flatten(-2)

    def rotate(x):
        """Rotate ``x`` in fp32 and cast back to its dtype."""
        xf = x.float()
        out = xf * cos
        swapped = xf.unflatten(-1, (-1, 2)).flip(-1).flatten(-2)
        swapped.mul_(sin_signed)
        out.add_(swapped)
        return out.type_as(x)

    return rotate(q), rotate(k)


#: complex pairs that ATen's CPU kernels multiply in vector registers only when a row or a thread's share of the
#: tensor is a multiple of it: two AVX-512 vectors of 8 pairs (AVX2's 4 divide it). A remainder goes through the
#: scalar ``c10::complex`` product, which the compiler may contract to a fused multiply-add, and then differs from
#: transformers' separately rounded products in the last bit (measured: head sizes 2-8, 2026-12-07).
_COMPLEX_VECTOR_PAIRS = 16
#: ATen's ``at::internal::GRAIN_SIZE``: below it an elementwise kernel runs on one thread
_ATEN_GRAIN = 32768


def _complex_rotation_is_exact(x, cos, sin, threads: int) -> bool:
    r"""Tell whether RoPE as a complex product gives transformers' rotation bit for bit.

    transformers computes :math:`(x_{2i} c_{2i} - x_{2i+1} s_{2i},\ x_{2i+1} c_{2i+1} + x_{2i} s_{2i+1})`, each
    product rounded, then the sum; ATen's vectorised complex product :math:`(x_{2i} + i\,x_{2i+1})(c + i\,s)`
    rounds the same products and sums in the same way (no fused multiply-add), which is that rotation wherever
    ``cos`` and ``sin`` repeat each value for a pair (SAM 3's ``recomposition_frequencies`` does). Its scalar tail may
    fuse, so every row and every thread's share (ATen's OpenMP split: ``ceil(n / min(threads, ceil(n / grain)))``
    pairs) must be a multiple of :data:`_COMPLEX_VECTOR_PAIRS`. tests/teachers/test_sam3_patches.py holds this
    against transformers' function at several head sizes and thread counts.

    Parameters
    ----------
    x : torch.Tensor
        The query, ``[..., head_dim]`` (the caller checks that the key has its shape).
    cos, sin : torch.Tensor
        ``[..., head_dim]``, broadcast against ``x``.
    threads : int
        torch's intra-op threads.

    Returns
    -------
    bool
        Whether the complex product applies.
    """
    import torch

    pairs = x.shape[-1] // 2
    if x.shape[-1] % 2 or pairs % _COMPLEX_VECTOR_PAIRS or x.device.type != "cpu":
        return False
    n = x.numel() // 2
    if threads > 1 and n >= _ATEN_GRAIN and -(-n // min(threads, -(-n // _ATEN_GRAIN))) % _COMPLEX_VECTOR_PAIRS:
        return False
    return bool(torch.equal(cos[..., 0::2], cos[..., 1::2]) and torch.equal(sin[..., 0::2], sin[..., 1::2]))


def _window_partition_no_empty_pad(hidden_state, window_size):
    """Partition like transformers' ``window_partition``, without its ``F.pad`` copy when nothing is padded.

    SAM 3's 72 x 72 tokens fall in 24 x 24 windows: the same windows, one copy fewer per windowed layer.
    """
    import torch.nn.functional as F

    batch_size, height, width, num_channels = hidden_state.shape
    pad_height = (window_size - height % window_size) % window_size
    pad_width = (window_size - width % window_size) % window_size
    if pad_height or pad_width:
        hidden_state = F.pad(hidden_state, (0, 0, 0, pad_width, 0, pad_height))
    padded_height, padded_width = height + pad_height, width + pad_width
    hidden_state = hidden_state.view(
        batch_size, padded_height // window_size, window_size, padded_width // window_size, window_size, num_channels)
    windows = hidden_state.permute(0, 1, 3, 2, 4, 5).contiguous().view(-1, window_size, window_size, num_channels)
    return windows, (padded_height, padded_width)


def _embed_pixels_no_clone(self, backbone_features, encoder_hidden_states):
    """Embed pixels like transformers' ``Sam3MaskDecoder._embed_pixels``, without cloning every FPN level.

    The pixel decoder only reads the levels (its sums make new tensors), so a list of the same tensors gives the
    same answer, with no copy per (image, prompt).
    """
    backbone_visual_feats = list(backbone_features)
    spatial_dim = backbone_features[-1].shape[-2] * backbone_features[-1].shape[-1]
    encoder_visual_embed = encoder_hidden_states[:, :spatial_dim, :]
    batch_size, _, hidden_size = encoder_visual_embed.shape
    height, width = backbone_features[-1].shape[-2:]
    encoder_visual_embed = encoder_visual_embed.transpose(1, 2).reshape(batch_size, hidden_size, height, width)
    backbone_visual_feats[-1] = encoder_visual_embed
    return self.pixel_decoder(backbone_visual_feats)


def _rpb_matrix_one_pass(self, reference_boxes, spatial_shape):
    """Compute transformers' ``Sam3DetrDecoder._get_rpb_matrix`` with its last sum written in its final layout.

    The sum goes straight into the [batch, heads, queries, height * width] layout the attention reads, instead of
    summing in [batch, queries, height, width, heads] and copying with ``.permute(...).contiguous()``: the same
    sums, one pass over the largest tensor of the DETR decoder fewer per layer. Its two operands are laid out
    heads-major first, so the sum runs along contiguous rows (vectorised) instead of striding by the head count
    (28.8 → 13.3 ms a layer at real size, bf16, 2 AMX cores).
    """
    import torch
    from transformers.models.sam3.modeling_sam3 import box_cxcywh_to_xyxy

    height, width = spatial_shape
    boxes_xyxy = box_cxcywh_to_xyxy(reference_boxes)
    batch_size, num_queries, _ = boxes_xyxy.shape
    coords_h, coords_w = self._get_coords(height, width, dtype=reference_boxes.dtype, device=reference_boxes.device)
    deltas_y = coords_h.view(1, -1, 1) - boxes_xyxy.reshape(-1, 1, 4)[:, :, 1:4:2]
    deltas_y = deltas_y.view(batch_size, num_queries, -1, 2)
    deltas_x = coords_w.view(1, -1, 1) - boxes_xyxy.reshape(-1, 1, 4)[:, :, 0:3:2]
    deltas_x = deltas_x.view(batch_size, num_queries, -1, 2)
    deltas_x_log = deltas_x * 8
    deltas_x_log = torch.sign(deltas_x_log) * torch.log2(torch.abs(deltas_x_log) + 1.0) / math.log2(8)
    deltas_y_log = deltas_y * 8
    deltas_y_log = torch.sign(deltas_y_log) * torch.log2(torch.abs(deltas_y_log) + 1.0) / math.log2(8)
    deltas_x = self.box_rpb_embed_x(deltas_x_log)  # [batch_size, num_queries, width, num_heads]
    deltas_y = self.box_rpb_embed_y(deltas_y_log)  # [batch_size, num_queries, height, num_heads]
    rows, cols, heads = deltas_y.shape[2], deltas_x.shape[2], deltas_x.shape[3]
    rpb_matrix = torch.empty(batch_size, heads, num_queries, rows * cols,
                             dtype=torch.result_type(deltas_y, deltas_x), device=deltas_x.device)
    # heads-major first (small tensors), so the sum's innermost dimension is contiguous in every operand
    deltas_y, deltas_x = deltas_y.permute(0, 3, 1, 2).contiguous(), deltas_x.permute(0, 3, 1, 2).contiguous()
    torch.add(deltas_y.unsqueeze(-1), deltas_x.unsqueeze(-2), out=rpb_matrix.view(batch_size, heads, num_queries,
                                                                                    rows, cols))
    return rpb_matrix


#: what :func:`exact_savings` replaces in transformers' ``modeling_sam3``: (owner name, attribute) -> (the
#: replacement, sha256 of the upstream source it was written against). A transformers whose source differs
#: keeps its own code (the saving is lost, never the answer); tests/teachers/test_sam3_patches.py fails then.
SAM3_PATCHES = {
    ("modeling_sam3", "apply_rotary_pos_emb_2d"): (
        _rope_fewer_passes, "1fa3bc56888d6f69e291a7651315a43ea1c3f5f7e175d3a7143e2a0054ffe7dc"),
    ("modeling_sam3", "window_partition"): (
        _window_partition_no_empty_pad, "b28eb8bc3a59517f7446bcf78ac96568cfd676e8fef180fe2e9811fd8208d1b9"),
    ("Sam3DetrDecoder", "_get_rpb_matrix"): (
        _rpb_matrix_one_pass, "223c200503a5510cc5f7530f166c77d98bd70ded4abe29cabb8022f2647ed770"),
    ("Sam3MaskDecoder", "_embed_pixels"): (
        _embed_pixels_no_clone, "c3953291fe55957f22f7aa0a68a63156fc70174e95e3f37f9df4036080f01342"),
}


def upstream_source_digest(owner: str, name: str) -> str | None:
    """Hash the source of a function or method of transformers' ``modeling_sam3``.

    Parameters
    ----------
    owner : str
        ``"modeling_sam3"`` for a module-level function, else the class name in that module.
    name : str
        The function's or method's name.

    Returns
    -------
    str or None
        The hex sha256 of ``modeling_sam3.<name>``'s or ``modeling_sam3.<owner>.<name>``'s source; None when
        transformers has no such function or method, or its source cannot be read.
    """
    import transformers.models.sam3.modeling_sam3 as modeling

    target = modeling if owner == "modeling_sam3" else getattr(modeling, owner, None)
    fn = getattr(target, name, None) if target is not None else None
    if fn is None:
        return None
    try:
        return hashlib.sha256(inspect.getsource(fn).encode()).hexdigest()
    except (OSError, TypeError):
        return None


#: the Sam3Model attribute holding each patched class's instance (its method is replaced on that instance only)
_INSTANCE_OWNERS = {"Sam3DetrDecoder": "detr_decoder", "Sam3MaskDecoder": "mask_decoder"}
_PATCHES_THAT_FIT: list | None = None


def _patches_that_fit() -> list:
    """List the :data:`SAM3_PATCHES` whose upstream source is the one each was written against (checked once)."""
    global _PATCHES_THAT_FIT
    if _PATCHES_THAT_FIT is None:
        _PATCHES_THAT_FIT = [(owner, name, replacement)
                             for (owner, name), (replacement, digest) in SAM3_PATCHES.items()
                             if upstream_matches(owner, name, digest, "saving")]
    return _PATCHES_THAT_FIT


def upstream_matches(owner: str, name: str, digest: str, what: str) -> bool:
    """Tell whether transformers' source of ``owner.name`` is the one a replacement was written against.

    Where not, log that it is kept as is (the replacement is skipped: the saving is lost, never the answer).

    Parameters
    ----------
    owner, name : str
        As :func:`upstream_source_digest` takes them.
    digest : str
        The sha256 of the source the replacement was written against.
    what : str
        What the replacement is (``saving``, ``fusion``), for the log line.

    Returns
    -------
    bool
        Whether the source's digest is ``digest``.
    """
    if upstream_source_digest(owner, name) == digest:
        return True
    log.info("sam3: transformers' %s.%s differs from the code its %s was written for; kept as is", owner, name, what)
    return False


@contextlib.contextmanager
def exact_savings(model):
    """Run transformers' SAM 3 without the copies and memory passes it does not need, answers bit for bit the same.

    The same in fp32 and bf16 (issue 65 item 1; tests/teachers/test_sam3_patches.py): RoPE's rotation in fewer
    passes, no zero-padding copy before the window partition, the DETR decoder's box bias summed into its final
    layout, no clone of every FPN level in the mask decoder.

    The two module-level functions are swapped in ``modeling_sam3`` for the context's duration (one teacher per
    process calls the model; a second thread inside the context would see them too, with the same answers), the
    methods on ``model.detr_decoder`` and ``model.mask_decoder`` only. Only patches whose upstream source
    matches :data:`SAM3_PATCHES` apply.

    Parameters
    ----------
    model : transformers.Sam3Model
        The loaded model.

    Yields
    ------
    None
    """
    import transformers.models.sam3.modeling_sam3 as modeling

    saved, instance = [], []
    for owner, name, replacement in _patches_that_fit():
        if owner == "modeling_sam3":
            saved.append((name, getattr(modeling, name)))
            setattr(modeling, name, replacement)
        elif owner in _INSTANCE_OWNERS and getattr(model, _INSTANCE_OWNERS[owner], None) is not None:
            module = getattr(model, _INSTANCE_OWNERS[owner])
            setattr(module, name, types.MethodType(replacement, module))
            instance.append((module, name))
    try:
        yield
    finally:
        for name, original in saved:
            setattr(modeling, name, original)
        for obj, name in instance:
            delattr(obj, name)


#: what the onednn engine adds to the teacher's path and fingerprint
ONEDNN_PATH = "onednn fused MLP activations"
#: transformers' ``Sam3MLP.forward`` as :func:`fused_mlp_activations` was written against (fc1, dropout, the
#: activation, fc2); a transformers whose source differs keeps its own MLPs (tests/teachers/test_sam3_patches.py fails)
FUSED_MLP_TARGET = ("Sam3MLP", "forward", "e47b656ce6cca5d4216c4cac51512d1a37aec38300e69180032a13a366106afa")


def onednn_post_op(activation) -> tuple[str, str] | None:
    """Name oneDNN's post-op for an MLP's activation module.

    Parameters
    ----------
    activation : torch.nn.Module
        The MLP's ``activation_fn``.

    Returns
    -------
    tuple of (str, str) or None
        (attribute, algorithm) of ``torch.ops.mkldnn._linear_pointwise``: ``("relu", "")`` for ``nn.ReLU``,
        ``("gelu", "none")`` for transformers' exact (erf) GELU; None for any other activation.
    """
    import torch
    from transformers.activations import GELUActivation

    if type(activation) is torch.nn.ReLU:
        return "relu", ""
    if type(activation) is GELUActivation and activation.act is torch.nn.functional.gelu:
        return "gelu", "none"
    return None


def _fused_mlp_forward(self, hidden_states, post_op: tuple[str, str]):
    """Compute ``Sam3MLP.forward`` with ``activation(fc1(x))`` in one oneDNN kernel.

    ``post_op`` is the MLP's :func:`onednn_post_op`, found once when the forward is patched. The activation runs on
    the fp32 accumulator before the one rounding to bf16, instead of on the rounded bf16 output in a second pass
    (ReLU: the same bits; GELU: one rounding fewer). Anything but a bf16 CPU tensor in eval mode runs upstream's
    code.
    """
    import torch

    if self.training or hidden_states.dtype != torch.bfloat16 or hidden_states.device.type != "cpu":
        return type(self).forward(self, hidden_states)
    shape = hidden_states.shape
    fused = torch.ops.mkldnn._linear_pointwise(hidden_states.reshape(-1, shape[-1]), self.fc1.weight, self.fc1.bias,
                                               post_op[0], [], post_op[1])
    return self.fc2(fused.view(*shape[:-1], -1))  # dropout: identity in eval mode


@functools.cache
def _fused_mlp_fits() -> bool:
    """Whether transformers' ``Sam3MLP.forward`` is the source :data:`FUSED_MLP_TARGET` names (checked once)."""
    return upstream_matches(*FUSED_MLP_TARGET, "fusion")


@contextlib.contextmanager
def fused_mlp_activations(model):
    """Run each ``Sam3MLP``'s activation inside its first linear layer's oneDNN kernel (``teacher.engine: onednn``).

    The backbone's 32 MLPs (GELU) and the DETR encoder's and decoder's (ReLU) apply their activation as a separate
    pass over the largest tensors of the model, 4736 and 2048 channels wide; oneDNN applies it to the accumulator
    in the matmul's own pass. On a 2-core AMX host, real size, one 256² image and six prompts: 10.65 -> 9.66 s per
    image against the torch engine (docs/performance.md, "The teacher on AMX"). Not bit-identical in bf16 (GELU
    is applied before the output's rounding, not after it): the fidelity gate holds it
    (tests/teachers/test_teacher_cpu_dtype.py, ``bench_teacher --roofline``). The forward is replaced on each
    instance for the context's duration; a transformers whose ``Sam3MLP.forward`` differs from
    :data:`FUSED_MLP_TARGET`'s source keeps its own.

    Parameters
    ----------
    model : transformers.Sam3Model
        The loaded model, whose ``Sam3MLP`` modules run fused inside the context.

    Yields
    ------
    int
        The MLPs fused (0 where the upstream source differs).
    """
    import transformers.models.sam3.modeling_sam3 as modeling

    mlps = {}
    if _fused_mlp_fits():
        mlps = {m: op for m in model.modules()
                if isinstance(m, modeling.Sam3MLP) and (op := onednn_post_op(m.activation_fn)) is not None}
    for m, op in mlps.items():  # an instance attribute: nn.Module.__call__ reads it
        m.forward = types.MethodType(functools.partial(_fused_mlp_forward, post_op=op), m)
    try:
        yield len(mlps)
    finally:
        for m in mlps:
            del m.forward


class Sam3Teacher(RegisteredTeacher):
    r"""Frozen SAM 3 answering text prompts: vision encoder once per image batch, text features once per run.

    eq:teacher-prediction: each (image, prompt) gets the best query's mask and score
    :math:`\sigma(\ell_q)\,\sigma(\ell_{presence})`, invalid (score 0, empty mask) at or below
    ``score_threshold``.

    Parameters
    ----------
    checkpoint : str or Path
        A local SAM 3 checkpoint directory (:func:`check_checkpoint_dir`).
    device : str, optional
        ``auto``, ``cpu``, ``cuda``, ... (:func:`pipeline.runtime.device.resolve_device`).
    dtype : str, optional
        ``teacher.dtype``: ``auto``, ``fp32`` or ``bf16`` (:func:`resolve_teacher_dtype`).
    batch_size : int, optional
        Images per forward; 0: sized to the free GPU memory after one image (:func:`auto_batch_size`), 2 on a CPU.
    resolution : tuple of int or None, optional
        (H, W) of the working resolution, part of the fingerprint.
    score_threshold : float, optional
        A best score at or below it makes the prompt invalid.
    mask_threshold : float, optional
        Threshold on the best query's mask probability, upsampled to the image.
    hash_memo : str or Path or None, optional
        The checkpoint-hash memo file (:func:`memoised_checkpoint_hash`); None: hash each run.
    compile : bool, optional
        ``torch.compile`` the vision encoder; on a GPU only (ignored on a CPU).
    engine : str, optional
        ``teacher.engine``: ``auto``, ``torch``, ``openvino`` (the bf16 attention in OpenVINO) or ``onednn`` (the
        bf16 MLPs' activations fused by oneDNN; :func:`pipeline.teachers.attention.resolve_teacher_engine`).

    Attributes
    ----------
    checkpoint : Path
        The checked checkpoint directory.
    device : torch.device
        The resolved device.
    dtype_asked : str
        ``dtype`` as given.
    dtype_name : str
        The weights' dtype, ``fp32`` or ``bf16``.
    tf32 : bool
        Whether TF32 matmuls are on while predicting.
    torch_dtype : torch.dtype
        ``dtype_name`` as a torch dtype.
    batch_size : int
        Images per forward (0 until the first forward measures it on a GPU).
    compile : bool
        Whether the vision encoder is compiled.
    engine : str
        The resolved engine, ``torch``, ``openvino`` or ``onednn``.
    engine_note : str or None
        One line where the engine asked is not the one that runs (logged at load).
    runner_batch_size : int
        Images handed over per call by the teacher stage's runner (the cache's unit of work).
    resolution : tuple of int or None
        The working resolution.
    score_threshold, mask_threshold : float
        The thresholds.
    input_size : tuple of int
        (H, W) the images are resized to (the processor config's ``size``).
    do_resize, do_normalize : bool
        The processor config's switches.
    rescale : float
        The pixel scale factor (1 when the processor does not rescale).
    mean, std : torch.Tensor
        Normalisation [1,3,1,1].
    """

    backend = BACKEND

    @classmethod
    def from_params(cls, cfg, resolution: tuple[int, int], device: str = "auto") -> "Sam3Teacher":
        """Build the teacher of a validated ``teacher:`` section.

        Parameters
        ----------
        cfg : Mapping
            The validated ``teacher:`` section: its ``checkpoint``, ``dtype``, ``batch_size``, ``score_threshold``,
            ``mask_threshold``, ``compile``, ``engine`` and ``cache_dir`` (where the hash memo lives, :func:`local_hash_memo`).
        resolution : tuple of int
            (H, W) of the working resolution.
        device : str, optional
            The device to run on.

        Returns
        -------
        Sam3Teacher
            The teacher (its model is loaded on first use).
        """
        return cls(cfg["checkpoint"], device=device, dtype=cfg["dtype"], batch_size=cfg["batch_size"],
                   resolution=resolution, score_threshold=cfg["score_threshold"],
                   mask_threshold=cfg["mask_threshold"], compile=cfg["compile"], engine=cfg["engine"],
                   hash_memo=local_hash_memo(cfg["cache_dir"]))

    def __init__(self, checkpoint: str | Path, *, device: str = "auto", dtype: str = PAPER.teacher.dtype,
                 batch_size: int = PAPER.teacher.batch_size, resolution: tuple[int, int] | None = None,
                 score_threshold: float = PAPER.teacher.score_threshold,
                 mask_threshold: float = PAPER.teacher.mask_threshold, hash_memo: str | Path | None = None,
                 compile: bool = PAPER.teacher.compile, engine: str = PAPER.teacher.engine):
        """Check the checkpoint and read its processor config; the model is loaded on first use.

        Raises
        ------
        InputError
            The checkpoint is not a local SAM 3 checkpoint, its processor config is missing or unreadable or
            has no usable ``size``, or ``dtype`` or ``engine`` is unknown.
        """
        import torch

        self.checkpoint = check_checkpoint_dir(checkpoint)
        self.device = resolve_device(device)
        self.dtype_asked = dtype
        self.dtype_name, self.tf32 = resolve_teacher_dtype(dtype, self.device)
        self.torch_dtype = torch.bfloat16 if self.dtype_name == "bf16" else torch.float32
        self.batch_size = int(batch_size) if int(batch_size) > 0 else (0 if self.device.type == "cuda" else 2)
        self.compile = bool(compile) and self.device.type == "cuda"  # torch.compile pays on a GPU only
        self.engine, self.engine_note = resolve_teacher_engine(engine, self.device, self.dtype_name)
        # read once per teacher (a package lookup), not at every fingerprint
        self._openvino = attention.openvino_version() if self.engine == "openvino" else None
        self._attention = None  # OpenVINOAttention, made at load
        # images handed over per call by the teacher stage's runner (the cache's unit of work)
        self.runner_batch_size = self.batch_size or MAX_AUTO_BATCH
        self.resolution = tuple(resolution) if resolution is not None else None
        self.score_threshold = float(score_threshold)
        self.mask_threshold = float(mask_threshold)
        proc = read_processor_config(self.checkpoint)
        size = proc.get("size") or {}
        if "height" in size and "width" in size:
            self.input_size = (int(size["height"]), int(size["width"]))
        elif "longest_edge" in size or "shortest_edge" in size:
            e = int(size.get("longest_edge") or size.get("shortest_edge"))
            self.input_size = (e, e)
        else:
            raise InputError(f"{self.checkpoint}: processor config has no usable size {size!r}")
        self.do_resize = bool(proc.get("do_resize", True))
        self.rescale = float(proc.get("rescale_factor", 1 / 255)) if proc.get("do_rescale", True) else 1.0
        self.do_normalize = bool(proc.get("do_normalize", True))
        self.mean = torch.tensor(proc.get("image_mean", [0.5, 0.5, 0.5]), dtype=torch.float32).view(1, 3, 1, 1)
        self.std = torch.tensor(proc.get("image_std", [0.5, 0.5, 0.5]), dtype=torch.float32).view(1, 3, 1, 1)
        self._hash_memo = Path(hash_memo) if hash_memo is not None else None  # memoised_checkpoint_hash
        self._hash = self._model = self._tokenizer = None
        self._text: dict[tuple[str, ...], tuple] = {}

    def fingerprint(self) -> dict:
        """Describe what determines the answers (:meth:`pipeline.teachers.base.Teacher.fingerprint`).

        The checkpoint is hashed on the first call (memoised, :func:`memoised_checkpoint_hash`).

        Returns
        -------
        dict
            Backend, checkpoint hash, dtype (``+tf32`` when on), resolution, both thresholds and the prompts'
            token length; with the openvino engine also it and OpenVINO's version, with the onednn engine its
            fusion (the torch engine's fingerprint is the one from before the setting, so no cached answer is
            computed again).
        """
        if self._hash is None:
            log.info("sam3: hashing checkpoint %s for the cache key", self.checkpoint)
            self._hash = memoised_checkpoint_hash(self.checkpoint, self._hash_memo)
        return {"backend": BACKEND, "checkpoint": self._hash,
                "dtype": self.dtype_name + ("+tf32" if self.tf32 else ""),
                "resolution": list(self.resolution) if self.resolution else None,
                "score_threshold": self.score_threshold, "mask_threshold": self.mask_threshold,
                "text_max_length": TEXT_MAX_LENGTH,
                **({"engine": "openvino attention", "openvino": self._openvino} if self.engine == "openvino"
                   else {"engine": ONEDNN_PATH} if self.engine == "onednn" else {})}

    def _fused(self, model):
        """Return the context of ``teacher.engine: onednn`` (:func:`fused_mlp_activations`), a no-op otherwise."""
        return fused_mlp_activations(model) if self.engine == "onednn" else contextlib.nullcontext()

    def path(self) -> str:
        """Name the path the answers take, as ``label``'s projection and summary name it.

        Returns
        -------
        str
            Backend, engine, dtype and device, e.g. ``sam3 torch eager bf16 + openvino attention on cpu`` or
            ``sam3 torch eager bf16 + onednn fused MLP activations on cpu``.
        """
        return (f"{BACKEND} torch {'compiled' if self.compile else 'eager'} {self.dtype_name}"
                f"{'+tf32' if self.tf32 else ''}{' + openvino attention' if self.engine == 'openvino' else ''}"
                f"{' + ' + ONEDNN_PATH if self.engine == 'onednn' else ''} on {self.device.type}")

    def cache_note(self) -> str | None:
        """Say why a CPU's answers cached before ``auto`` chose bf16 or another engine there are computed again.

        Returns
        -------
        str or None
            The note (the dtype and the engine are part of the fingerprint); None where ``auto`` still means fp32
            and torch, or both were pinned.
        """
        notes = []
        if self.dtype_asked == "auto" and self.device.type == "cpu" and self.dtype_name == "bf16":
            notes.append("teacher.dtype auto is bf16 on this CPU (native bf16 units): answers cached under fp32 are "
                         "not reused; set teacher.dtype: fp32 to keep them")
        if self.engine == "openvino":
            notes.append("teacher.engine runs the attention in OpenVINO: answers cached by the torch engine are not "
                         "reused; set teacher.engine: torch to keep them")
        if self.engine == "onednn":
            notes.append(f"teacher.engine runs the {ONEDNN_PATH}: answers cached by the torch engine are not "
                         "reused; set teacher.engine: torch to keep them")
        return "; ".join(notes) or None

    def load(self):
        """Load model and tokenizer once (local files only), on the device, in eval mode.

        Returns
        -------
        transformers.Sam3Model
            The model (its vision encoder compiled where ``compile``).

        Raises
        ------
        InputError
            transformers has no SAM 3 (needs >= 5), or the checkpoint cannot be loaded (naming it and why).
        """
        if self._model is None:
            import torch

            try:
                from transformers import AutoTokenizer, Sam3Model
            except ImportError as e:
                raise InputError(f"teacher.backend=sam3 needs transformers>=5 with SAM 3 "
                                 f"(pip install '.[sam3]'): {e}") from None
            reuse_freed_memory(self.device)  # on a CPU each call reuses what the last one freed: the same answers
            try:
                with library_bars_off():  # no "Loading weights" bar of transformers' own
                    model = Sam3Model.from_pretrained(self.checkpoint, local_files_only=True, dtype=self.torch_dtype)
                    self._tokenizer = AutoTokenizer.from_pretrained(self.checkpoint, local_files_only=True)
            except (OSError, ValueError) as e:
                raise InputError(f"{self.checkpoint}: cannot load SAM 3 checkpoint "
                                 f"({type(e).__name__}: {str(e).splitlines()[0][:200]})") from None
            model = model.to(self.device).eval()
            if self.compile:  # the vision encoder: about half the time, 2.3x faster compiled (H100, bf16)
                model.vision_encoder = torch.compile(model.vision_encoder)
            if self.engine_note:
                log.warning("sam3: %s", self.engine_note)
            if self.engine == "openvino":
                from transformers.integrations.sdpa_attention import sdpa_attention_forward

                self._attention = OpenVINOAttention(sdpa_attention_forward, torch.get_num_threads())
            self._model = model
        return self._model

    def text_features(self, prompts: Sequence[str]):
        """Encode ``prompts`` once per run (remembered per prompt tuple).

        Parameters
        ----------
        prompts : sequence of str
            The K prompts, padded or truncated to :data:`TEXT_MAX_LENGTH` tokens.

        Returns
        -------
        tuple of torch.Tensor
            Projected text features [K,L,D] and attention mask [K,L].
        """
        import torch

        key = tuple(prompts)
        if key not in self._text:
            model = self.load()
            tok = self._tokenizer(list(prompts), padding="max_length", max_length=TEXT_MAX_LENGTH,
                                  truncation=True, return_tensors="pt")
            ids = tok["input_ids"].to(self.device)
            mask = tok["attention_mask"].to(self.device)
            with torch.inference_mode():
                feats = model.get_text_features(input_ids=ids, attention_mask=mask, return_dict=True).pooler_output
            self._text[key] = (feats, mask)
        return self._text[key]

    def preprocess(self, images: Sequence[np.ndarray]):
        """Turn images into the model's pixel values: resize, rescale, normalise (no torchvision).

        Parameters
        ----------
        images : sequence of numpy.ndarray
            B uint8 [H,W,3] images of one size.

        Returns
        -------
        torch.Tensor
            pixel_values [B,3,S,S] on the device, in the weights' dtype.
        """
        import torch
        import torch.nn.functional as F

        x = torch.from_numpy(np.stack([np.asarray(im, dtype=np.uint8) for im in images])).permute(0, 3, 1, 2)
        x = x.to(self.device, torch.float32)
        if self.do_resize and tuple(x.shape[-2:]) != self.input_size:
            x = F.interpolate(x, size=self.input_size, mode="bilinear", align_corners=False, antialias=True)
        x = x * self.rescale
        if self.do_normalize:
            x = (x - self.mean.to(x.device)) / self.std.to(x.device)
        return x.to(self.torch_dtype)

    def encode_images(self, images: Sequence[np.ndarray]):
        """Run the vision encoder over a batch of images (one pass, reused by every prompt).

        Parameters
        ----------
        images : sequence of numpy.ndarray
            B uint8 [H,W,3] images of one size.

        Returns
        -------
        transformers.models.sam3.modeling_sam3.Sam3VisionEncoderOutput
            The vision features of the B images.
        """
        import torch

        model = self.load()
        with torch.inference_mode(), exact_savings(model), attention_engine(self._attention), self._fused(model):
            return model.get_vision_features(pixel_values=self.preprocess(images))

    @staticmethod
    def _repeat_vision(vision, k: int):
        """Repeat each image's FPN features for its ``k`` prompts: batch B -> B*k (image-major).

        One image: views that repeat nothing in memory (stride 0 over the prompts; the model only reads them, and
        the DETR encoder's flattening copies its level once), so the same answers without writing every level k
        times.
        """
        from transformers.models.sam3.modeling_sam3 import Sam3VisionEncoderOutput

        if vision.fpn_hidden_states[0].shape[0] == 1:
            rep = lambda ts: tuple(t.expand(k, *t.shape[1:]) for t in ts)  # noqa: E731
        else:
            rep = lambda ts: tuple(t.repeat_interleave(k, dim=0) for t in ts)  # noqa: E731
        return Sam3VisionEncoderOutput(last_hidden_state=vision.last_hidden_state,
                                       fpn_hidden_states=rep(vision.fpn_hidden_states),
                                       fpn_position_encoding=rep(vision.fpn_position_encoding))

    def heads(self, vision, prompts: Sequence[str], n_images: int, out_size: tuple[int, int]):
        """Run the detector heads for every (image, prompt) and keep each one's best query (eq:teacher-prediction).

        Parameters
        ----------
        vision : Sam3VisionEncoderOutput
            :meth:`encode_images` of the ``n_images`` images.
        prompts : sequence of str
            The K prompts.
        n_images : int
            B, the images ``vision`` holds.
        out_size : tuple of int
            (H, W) the masks are upsampled to.

        Returns
        -------
        tuple of numpy.ndarray
            Masks bool [B,K,H,W] and scores float32 [B,K]; a score at or below ``score_threshold`` is 0, its mask
            empty (:func:`pipeline.teachers.base.finalize_answers`).
        """
        import torch
        import torch.nn.functional as F
        from transformers.modeling_outputs import BaseModelOutputWithPooling

        model = self.load()
        k = len(prompts)
        feats, mask = self.text_features(prompts)
        text = BaseModelOutputWithPooling(pooler_output=feats.repeat(n_images, 1, 1))
        with torch.inference_mode(), first_self_attention_once_per_image(model, k), exact_savings(model), \
                attention_engine(self._attention), self._fused(model):
            out = model(vision_embeds=self._repeat_vision(vision, k), text_embeds=text,
                        attention_mask=mask.repeat(n_images, 1))
            scores = out.pred_logits.float().sigmoid()                       # [B*K, Q]
            if out.presence_logits is not None:
                scores = scores * out.presence_logits.float().sigmoid()      # [B*K, 1] broadcast
            best_score, best = scores.max(dim=1)
            best_mask = out.pred_masks[torch.arange(best.shape[0], device=best.device), best]  # [B*K, h, w]
            prob = F.interpolate(best_mask[:, None].float().sigmoid(), size=out_size, mode="bilinear",
                                 align_corners=False)[:, 0]
            masks = (prob > self.mask_threshold).cpu().numpy().reshape(n_images, k, *out_size)
        best_score = best_score.cpu().numpy().astype(np.float32).reshape(n_images, k)
        # no candidate above the detection threshold -> invalid prompt (score 0, empty mask)
        best_score = np.where(best_score > self.score_threshold, best_score, 0.0).astype(np.float32)
        return finalize_answers(masks, best_score)

    def predict(self, batch: Sequence[TeacherInput], prompts: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """Answer all prompts for all images, ``batch_size`` images per forward (vision encoded once per image).

        With ``batch_size`` 0 the first forward holds one image and sizes the rest (:func:`auto_batch_size`).

        Parameters
        ----------
        batch : sequence of TeacherInput
            B images of one size, each in its view.
        prompts : sequence of str
            The K prompts.

        Returns
        -------
        tuple of numpy.ndarray
            Masks bool [B,K,H,W] and scores float32 [B,K] (eq:teacher-prediction; 0 = invalid).

        Raises
        ------
        InputError
            The images of ``batch`` differ in size.
        """
        if not batch:
            return np.zeros((0, len(prompts), 0, 0), bool), np.zeros((0, len(prompts)), np.float32)
        out_size = tuple(batch[0].image.shape[:2])
        if any(tuple(it.image.shape[:2]) != out_size for it in batch):
            raise InputError("sam3: images of one batch differ in size")
        answers, i = [], 0
        with allow_tf32(self.tf32):
            while i < len(batch):
                measure = self.batch_size == 0  # one image, then batches sized to the free memory
                if measure:
                    import torch

                    self.load()
                    self.text_features(prompts)
                    torch.cuda.reset_peak_memory_stats(self.device)
                chunk = [it.image for it in batch[i:i + (self.batch_size or 1)]]
                answers.append(self.heads(self.encode_images(chunk), prompts, len(chunk), out_size))
                if measure:
                    self.batch_size = auto_batch_size(self.device)
                i += len(chunk)
        masks, scores = zip(*answers)
        return np.concatenate(masks), np.concatenate(scores)

    def predict_one_prompt_at_a_time(self, batch: Sequence[TeacherInput], prompts: Sequence[str]):
        """Answer like :meth:`predict` with one full forward per image and prompt, no feature reuse.

        The reference path of the tests and the benchmark: the same answers as :meth:`predict`.

        Parameters
        ----------
        batch : sequence of TeacherInput
            B images of one size (not empty).
        prompts : sequence of str
            The K prompts.

        Returns
        -------
        tuple of numpy.ndarray
            Masks bool [B,K,H,W] and scores float32 [B,K].
        """
        out_size = tuple(batch[0].image.shape[:2])
        masks = np.zeros((len(batch), len(prompts), *out_size), bool)
        scores = np.zeros((len(batch), len(prompts)), np.float32)
        for b, it in enumerate(batch):
            for k, p in enumerate(prompts):
                vision = self.encode_images([it.image])
                m, s = self.heads(vision, [p], 1, out_size)
                masks[b, k], scores[b, k] = m[0, 0], s[0, 0]
        return masks, scores
