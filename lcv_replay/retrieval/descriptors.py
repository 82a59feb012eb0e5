"""Global image descriptors for place recognition (paper sec. II-B, step 1).

A backend turns a batch of images into L2-normalised vectors::

    backend = make_backend("efficientnet-lite0", config)
    vectors = backend.describe([image_a, image_b])      # (2, backend.dim) float32, unit norm

Registered backends (:func:`available_backends`):

* ``efficientnet-lite0`` (default): ImageNet EfficientNet-Lite0 pooled conv features, run with
  torch on the CPU (:mod:`lcv_replay.retrieval.efficientnet`).
* ``thumbnail``: weight-free SeqSLAM-style patch-normalised thumbnails (Milford & Wyeth 2012),
  a measured baseline and a fast stand-in for tests.

Images are ``(H, W)`` grey or ``(H, W, 3)`` RGB uint8 arrays. Other sizes, channel counts and
dtypes are converted as the backend needs (grey is replicated to RGB for the CNN; RGBA loses its
alpha; uint16 and float images are rescaled to 8 bits), with one warning per backend.
"""

from __future__ import annotations

import logging
import time
from typing import Callable, Protocol, Sequence, runtime_checkable

import numpy as np

from lcv_replay.errors import RetrievalError
from lcv_replay.retrieval.config import RetrievalConfig

log = logging.getLogger(__name__)


@runtime_checkable
class DescriptorBackend(Protocol):
    """An image-to-vector function with a name (used in cache keys and reports).

    Attributes:
        name: registry name, e.g. ``"efficientnet-lite0"``.
        dim: descriptor length ``D``.
        input_size_px: the backend's input size (square CNN input, or thumbnail width).
    """

    name: str
    dim: int
    input_size_px: int

    def describe(self, images: Sequence[np.ndarray]) -> np.ndarray:
        """``B`` images -> ``(B, D)`` float32 L2-normalised descriptors."""
        ...


BackendFactory = Callable[[RetrievalConfig], DescriptorBackend]
_REGISTRY: dict[str, tuple[BackendFactory, str]] = {}


def register_backend(name: str, *, help: str) -> Callable[[BackendFactory], BackendFactory]:
    """Decorator registering a backend factory ``config -> DescriptorBackend`` under ``name``."""

    def decorator(factory: BackendFactory) -> BackendFactory:
        _REGISTRY[name] = (factory, help)
        return factory

    return decorator


def available_backends() -> dict[str, str]:
    """Registered backend names and their one-line help."""
    return {name: help for name, (_, help) in _REGISTRY.items()}


def make_backend(name: str, config: RetrievalConfig | None = None) -> DescriptorBackend:
    """Build the backend ``name`` (see :func:`available_backends`).

    Raises:
        RetrievalError: unknown name, or a missing package (the message names what to install).
    """
    config = config or RetrievalConfig()
    if name not in _REGISTRY:
        raise RetrievalError(
            f"unknown descriptor backend '{name}'", fix=f"use one of {', '.join(sorted(_REGISTRY))}"
        )
    factory, _ = _REGISTRY[name]
    return factory(config)


def l2_normalise(vectors: np.ndarray) -> np.ndarray:
    """``(B, D)`` rows scaled to unit L2 norm (all-zero rows stay zero)."""
    vectors = np.asarray(vectors, dtype=np.float32)
    norms = np.linalg.norm(vectors, axis=1, keepdims=True)
    return vectors / np.maximum(norms, 1e-12)


class ImageAdapter:
    """Converts input images to the size, channels and dtype a backend expects, warning once.

    Args:
        backend_name: named in the warning.
        width_px, height_px: the backend's input size.
        channels: 3 (RGB) or 1 (grey).
    """

    def __init__(self, backend_name: str, *, width_px: int, height_px: int, channels: int):
        self.backend_name = backend_name
        self.width_px = width_px
        self.height_px = height_px
        self.channels = channels
        self._warned: set[str] = set()

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """One image -> ``(height_px, width_px, 3)`` or ``(height_px, width_px)`` uint8."""
        import cv2

        image = np.asarray(image)
        if image.ndim == 3 and image.shape[2] == 1:
            image = image[:, :, 0]
        if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (3, 4)) or min(image.shape[:2]) < 1:
            raise RetrievalError(
                f"cannot describe an image of shape {image.shape}",
                fix="pass (H, W) grey or (H, W, 3) RGB images",
            )
        notes = []
        if image.dtype != np.uint8:
            notes.append(("dtype", f"{image.dtype} pixels rescaled to uint8"))
            image = _to_uint8(image)
        if image.ndim == 3 and image.shape[2] == 4:
            notes.append(("alpha", "alpha channel dropped"))
            image = image[:, :, :3]
        if self.channels == 3 and image.ndim == 2:
            notes.append(("channels", "grey replicated to 3 channels"))
            image = np.repeat(image[:, :, None], 3, axis=2)
        elif self.channels == 1 and image.ndim == 3:
            notes.append(("channels", "RGB converted to grey"))
            image = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
        height, width = image.shape[:2]
        if (width, height) != (self.width_px, self.height_px):
            notes.append(("resize", f"{width}x{height} resized to {self.width_px}x{self.height_px}"))
            shrink = width >= self.width_px and height >= self.height_px
            image = cv2.resize(
                np.ascontiguousarray(image),
                (self.width_px, self.height_px),
                interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR,
            )
        for key, note in notes:
            if key not in self._warned:
                self._warned.add(key)
                log.warning("%s: input images converted: %s (said once)", self.backend_name, note)
        return image


def _to_uint8(image: np.ndarray) -> np.ndarray:
    if image.dtype == np.uint16:
        return (image >> 8).astype(np.uint8)
    if np.issubdtype(image.dtype, np.floating):
        finite = np.nan_to_num(image.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        scale = 255.0 if finite.size and finite.max() <= 1.0 else 1.0
        return np.clip(finite * scale + 0.5, 0, 255).astype(np.uint8)
    if image.dtype == np.bool_:
        return image.astype(np.uint8) * 255
    return np.clip(image, 0, 255).astype(np.uint8)


# --- thumbnail (SeqSLAM) --------------------------------------------------------------------------


def patch_normalise(thumbnail: np.ndarray, patch_px: int) -> np.ndarray:
    """SeqSLAM patch normalisation: each ``patch_px`` square to zero mean and unit variance.

    Args:
        thumbnail: ``(H, W)`` float image; edge patches may be smaller.

    Returns:
        ``(H, W)`` float32; flat patches become zero.
    """
    out = np.asarray(thumbnail, dtype=np.float32).copy()
    height, width = out.shape
    for y in range(0, height, patch_px):
        for x in range(0, width, patch_px):
            patch = out[y : y + patch_px, x : x + patch_px]
            std = float(patch.std())
            patch -= patch.mean()
            if std > 1e-6:
                patch /= std
            else:
                patch[...] = 0.0
    return out


class ThumbnailBackend:
    """SeqSLAM-style descriptor: a small grey thumbnail, patch-normalised, flattened, L2-normalised."""

    name = "thumbnail"

    def __init__(self, config: RetrievalConfig):
        self.width_px = config.thumbnail_width_px
        self.height_px = config.thumbnail_height_px
        self.patch_px = config.thumbnail_patch_px
        self.dim = self.width_px * self.height_px
        self.input_size_px = self.width_px
        self.signature = f"{self.width_px}x{self.height_px},patch={self.patch_px}"
        self._adapt = ImageAdapter(self.name, width_px=self.width_px, height_px=self.height_px, channels=1)
        self._adapt._warned.update(("resize", "channels"))  # always downsampled to grey: by design, no warning

    def describe(self, images: Sequence[np.ndarray]) -> np.ndarray:
        out = np.zeros((len(images), self.dim), dtype=np.float32)
        for i, image in enumerate(images):
            out[i] = patch_normalise(self._adapt(image), self.patch_px).reshape(-1)
        return l2_normalise(out)


@register_backend("thumbnail", help="weight-free SeqSLAM-style patch-normalised grey thumbnail (baseline)")
def _make_thumbnail(config: RetrievalConfig) -> DescriptorBackend:
    return ThumbnailBackend(config)


# --- EfficientNet-Lite0 ------------------------------------------------------------------------


class EfficientNetLite0Backend:
    """ImageNet EfficientNet-Lite0 features, pooled and L2-normalised, on the CPU.

    Two engines compute the same descriptor (``retrieval.engine``; ``"auto"`` = torch in mode
    "paper", ONNX Runtime otherwise):

    * ``"onnxruntime"``: the folded model exported to ONNX at first use and cached
      (:mod:`lcv_replay.retrieval.onnx_engine`); as fast as torch here, starts without importing torch,
      and never spins its threads (docs/retrieval.md).
      When it cannot run (no onnxruntime, a failed export) ``"auto"`` falls back to torch with a
      warning; an explicit ``"onnxruntime"`` is an error.
    * ``"torch"``: loads the packaged weights, folds BatchNorm and padding into the convolutions
      (exact, see :mod:`lcv_replay.retrieval.efficientnet`), switches to channels_last, tunes the
      allocator, the thread count and OpenMP's wait policy (passive: see ``tune_omp_wait``). ``precision = "bf16"`` and ``torch_compile`` are torch options
      and select it.

    Built once, with one warm-up batch (``warmup_s`` records the whole cost).

    Attributes:
        dim: 1280 for ``avg``/``gem`` pooling, 1904 for ``multi``.
        engine: the engine in use, ``"onnxruntime"`` or ``"torch"``.
        warmup_s: seconds spent building and warming up the model.
    """

    name = "efficientnet-lite0"

    def __init__(self, config: RetrievalConfig):
        from lcv_replay.retrieval import efficientnet as enet

        start = time.perf_counter()
        enet.tune_omp_wait()  # before anything imports torch (the ONNX export does, once)
        self._enet = enet
        self.input_size_px = config.input_size_px
        self.batch_size = config.batch_size
        self.pooling = enet.pooling_spec(config.pooling, config.gem_p)
        self.dim = self.pooling.dim
        self.precision = config.precision
        self.compiled = config.torch_compile
        self.engine = config.resolved_engine
        torch_only = [name for name, on in (("precision = 'bf16'", config.precision == "bf16"), ("torch_compile", config.torch_compile)) if on]
        if self.engine == "onnxruntime" and torch_only:
            if config.engine == "onnxruntime":
                raise RetrievalError(f"retrieval.{torch_only[0]} is a torch option", fix="set retrieval.engine = 'torch' or 'auto'")
            self.engine = "torch"
        self._onnx = None
        if self.engine == "onnxruntime":
            from lcv_replay.retrieval.onnx_engine import OnnxDescriptorModel

            try:
                self._onnx = OnnxDescriptorModel(self.input_size_px, self.pooling, num_threads=config.num_threads)
                self.num_threads = self._onnx.num_threads
            except RetrievalError as exc:
                if config.engine == "onnxruntime":
                    raise
                log.warning("%s: ONNX Runtime unavailable (%s); using torch", self.name, exc)
                self.engine = "torch"
        if self.engine == "torch":
            if config.tune_allocator:
                enet.tune_allocator()
            self.num_threads = enet.set_threads(config.num_threads)
            self._torch = enet.import_torch()
            reference = enet.load_reference_model(self.input_size_px)
            self.model = enet.build_folded_model(reference, taps=self.pooling.taps).to(memory_format=self._torch.channels_last)
            if self.compiled:
                self.model = enet.compile_model(self.model)
        self.signature = (
            f"pooling={self.pooling.method},p={self.pooling.gem_p:g},taps={'+'.join(self.pooling.taps)},norm=127/128,{self.precision}"
            + (",onnxruntime" if self.engine == "onnxruntime" else "")
        )
        self._adapt = ImageAdapter(self.name, width_px=self.input_size_px, height_px=self.input_size_px, channels=3)
        self.describe_prepared(np.zeros((self.batch_size, self.input_size_px, self.input_size_px, 3), np.uint8))
        self.warmup_s = time.perf_counter() - start

    def describe(self, images: Sequence[np.ndarray]) -> np.ndarray:
        if len(images) == 0:
            return np.zeros((0, self.dim), dtype=np.float32)
        batch = np.stack([self._adapt(image) for image in images])  # (B, S, S, 3) uint8
        out = np.empty((len(images), self.dim), dtype=np.float32)
        for start in range(0, len(images), self.batch_size):
            out[start : start + self.batch_size] = self.describe_prepared(batch[start : start + self.batch_size])
        return out

    def describe_prepared(self, batch: np.ndarray) -> np.ndarray:
        """``(B, S, S, 3)`` uint8 RGB at the input size -> ``(B, D)`` descriptors (one forward pass)."""
        if self._onnx is not None:
            return self._onnx(batch)
        torch = self._torch
        count = batch.shape[0]
        if self.compiled and count < self.batch_size:  # one static shape: no recompilation for a short batch
            batch = np.concatenate([batch, np.zeros((self.batch_size - count, *batch.shape[1:]), batch.dtype)])
        with torch.inference_mode():
            x = torch.from_numpy(np.ascontiguousarray(batch)).permute(0, 3, 1, 2)  # NHWC memory = channels_last
            x = (x.float() - self._enet.INPUT_MEAN) / self._enet.INPUT_STD
            if self.precision == "bf16":
                with torch.autocast("cpu", dtype=torch.bfloat16):
                    maps = self.model(x)
                maps = tuple(m.float() for m in maps)
            else:
                maps = self.model(x)
            return self._enet.pool_features(maps, self.pooling).numpy()[:count]


@register_backend("efficientnet-lite0", help="ImageNet EfficientNet-Lite0 pooled conv features (ONNX Runtime or torch, CPU)")
def _make_efficientnet_lite0(config: RetrievalConfig) -> DescriptorBackend:
    return EfficientNetLite0Backend(config)
