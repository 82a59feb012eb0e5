"""EfficientNet-Lite0 descriptors in ONNX Runtime: the default CPU engine (``retrieval.engine``).

The network ONNX Runtime runs is exported from the same folded torch model the torch engine runs
(:func:`lcv_replay.retrieval.efficientnet.build_folded_model`), with the input normalisation and the
pooling inside the graph: uint8 ``(B, S, S, 3)`` RGB images in, ``(B, D)`` L2-normalised
descriptors out. So the two engines compute the same function and differ only in float rounding
(tests: cosine >= 0.99999, max |Δ| <= 1e-5 on the RTAB-Map corridor).

**Export at first use, cached.** The first run exports the model (torch's TorchScript-based ONNX
exporter, a few seconds), checks it against torch on a random batch, and stores it as
``efficientnet-lite0-<key>.onnx`` with a ``.json`` sidecar (its BLAKE2b digest and what it was
made from) in ``$LCV_CACHE_DIR/onnx``, else ``$XDG_CACHE_HOME/lcv-replay/onnx``
(``~/.cache/lcv-replay/onnx``). ``<key>`` hashes everything the graph depends on: the weights
file's digest, the input size, the pooling (method, GeM p, taps) and :data:`EXPORT_FORMAT`. Later
runs load the file without importing torch. A file whose digest does not match its sidecar, or that
ONNX Runtime cannot load, is exported again with a warning. Writes are atomic, so concurrent runs
(a fleet) never read half a file.

**Threads.** One intra-op thread per available core (``retrieval.num_threads``, 0 = all), and no
spinning between calls, so the verifier that runs between descriptor batches gets the CPU back.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from pathlib import Path

import numpy as np

from lcv_replay.errors import RetrievalError
from lcv_replay.fileio import atomic_output, user_cache_dir, write_text_atomic
from lcv_replay.retrieval import efficientnet as enet

log = logging.getLogger(__name__)

EXPORT_FORMAT = 1  # bump when the exported graph changes meaning (input layout, preprocessing)
OPSET = 17
EXPORT_BATCH = 2  # the exported batch dimension is dynamic; this is only the tracing example
_COSINE_MIN = 0.99999  # an export that differs more from torch is refused (never cached)


def onnx_cache_dir() -> Path:
    """``$LCV_CACHE_DIR/onnx``, else ``$XDG_CACHE_HOME/lcv-replay/onnx`` (``~/.cache/lcv-replay/onnx``)."""
    return user_cache_dir("onnx")


def _file_digest(path: Path) -> str:
    digest = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


def export_key(input_size_px: int, pooling: enet.PoolingSpec) -> dict:
    """What the exported graph depends on (hashed into its file name; written into its sidecar)."""
    weights = Path(enet.weights_path())
    return {
        "format": EXPORT_FORMAT,
        "model": enet.MODEL_NAME,
        "weights_blake2b": _file_digest(weights),
        "input_size_px": int(input_size_px),
        "pooling": pooling.method,
        "gem_p": float(pooling.gem_p),
        "taps": list(pooling.taps),
        "input": "uint8 NHWC RGB, (x - 127) / 128 inside the graph",
    }


def exported_model_path(key: dict, folder: Path | None = None) -> Path:
    """The cache file of the export described by ``key``."""
    tag = hashlib.blake2b(json.dumps(key, sort_keys=True).encode(), digest_size=6).hexdigest()
    return (folder or onnx_cache_dir()) / f"{enet.MODEL_NAME}-{key['input_size_px']}px-{key['pooling']}-{tag}.onnx"


def export_descriptor_model(path: Path, key: dict, pooling: enet.PoolingSpec) -> dict:
    """Export the folded torch model (+ normalisation + pooling) to ``path``, atomically, with its sidecar.

    The export is run once in ONNX Runtime and compared with torch on a random batch; one that
    differs (cosine < 0.99999) is refused, not cached. Returns the sidecar dict.
    """
    torch = enet.import_torch()
    import warnings

    start = time.perf_counter()
    size = key["input_size_px"]
    reference = enet.load_reference_model(size)
    net = DescriptorNet(enet.build_folded_model(reference, taps=pooling.taps), pooling).eval()
    example = torch.from_numpy(np.random.default_rng(0).integers(0, 256, size=(EXPORT_BATCH, size, size, 3), dtype=np.uint8))
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path, force=True) as tmp:
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation notices
            try:
                torch.onnx.export(
                    net, (example,), str(tmp), dynamo=False, opset_version=OPSET,
                    input_names=["images"], output_names=["descriptors"],
                    dynamic_axes={"images": {0: "batch"}, "descriptors": {0: "batch"}},
                )
            except Exception as exc:  # exporter failures come in many types
                raise RetrievalError(f"exporting EfficientNet-Lite0 to ONNX failed: {exc}", fix="set retrieval.engine = 'torch'") from None
        with torch.no_grad():
            expected = net(example).numpy()
        got = _session(tmp, 1).run(None, {"images": example.numpy()})[0]
        cosine = float((got * expected).sum(axis=1).min())
        if not cosine >= _COSINE_MIN:
            raise RetrievalError(f"the ONNX export differs from torch (cosine {cosine:.6f})", fix="set retrieval.engine = 'torch'")
    sidecar = {**key, "blake2b": _file_digest(path), "torch": torch.__version__, "opset": OPSET,
               "check_cosine_min": cosine, "export_s": round(time.perf_counter() - start, 2)}
    write_text_atomic(path.with_suffix(".json"), json.dumps(sidecar, indent=2) + "\n")
    log.info("exported %s to ONNX in %.1f s: %s", enet.MODEL_NAME, sidecar["export_s"], path)
    return sidecar


def _session(path: Path, num_threads: int):
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = num_threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    options.log_severity_level = 3  # errors only
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def import_onnxruntime():
    try:
        import onnxruntime  # noqa: F401
    except ImportError:
        raise RetrievalError("retrieval.engine = 'onnxruntime' needs the onnxruntime package", fix="pip install onnxruntime, or set retrieval.engine = 'torch'") from None
    return onnxruntime


class OnnxDescriptorModel:
    """The exported descriptor network in an ONNX Runtime session (exported at first use, cached).

    Args:
        input_size_px: square input size.
        pooling: the descriptor's pooling (:func:`lcv_replay.retrieval.efficientnet.pooling_spec`).
        num_threads: intra-op threads (0 = one per available core).
        cache_dir: where exports live (default :func:`onnx_cache_dir`).

    Attributes:
        path: the ``.onnx`` file in use.
        exported: whether this run exported it (``False``: read from the cache).
    """

    def __init__(self, input_size_px: int, pooling: enet.PoolingSpec, *, num_threads: int = 0, cache_dir: Path | None = None):
        import_onnxruntime()
        self.num_threads = num_threads if num_threads > 0 else _available_cores()
        key = export_key(input_size_px, pooling)
        self.path = exported_model_path(key, cache_dir)
        self.exported = False
        problem = self._cache_problem(key)
        if problem is not None:
            if problem != "absent":
                log.warning("ONNX model cache %s: %s; exporting it again", self.path, problem)
            export_descriptor_model(self.path, key, pooling)
            self.exported = True
        try:
            self._session = _session(self.path, self.num_threads)
        except Exception as exc:  # a file that passed its digest but ONNX Runtime refuses
            if self.exported:
                raise RetrievalError(f"ONNX Runtime cannot load the exported model: {exc}", path=self.path, fix="set retrieval.engine = 'torch'") from None
            log.warning("ONNX model cache %s cannot be loaded (%s); exporting it again", self.path, exc)
            export_descriptor_model(self.path, key, pooling)
            self.exported = True
            self._session = _session(self.path, self.num_threads)

    def _cache_problem(self, key: dict) -> str | None:
        """``None`` when the cached export is usable, else why not (``"absent"`` when missing)."""
        sidecar_path = self.path.with_suffix(".json")
        if not self.path.is_file() or not sidecar_path.is_file():
            return "absent"
        try:
            sidecar = json.loads(sidecar_path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            return f"unreadable sidecar ({exc})"
        if any(sidecar.get(k) != v for k, v in key.items()):
            return "sidecar does not match the model"
        if sidecar.get("blake2b") != _file_digest(self.path):
            return "checksum mismatch (damaged file)"
        return None

    def __call__(self, batch: np.ndarray) -> np.ndarray:
        """``(B, S, S, 3)`` uint8 RGB -> ``(B, D)`` float32 descriptors."""
        return self._session.run(None, {"images": np.ascontiguousarray(batch, dtype=np.uint8)})[0]


def _available_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def _make_descriptor_net_class():
    torch = enet.import_torch()

    class DescriptorNet(torch.nn.Module):
        """uint8 ``(B, S, S, 3)`` RGB -> ``(B, D)`` descriptors: normalisation, folded network, pooling."""

        def __init__(self, folded, pooling: enet.PoolingSpec):
            super().__init__()
            self.folded = folded
            self.pooling = pooling

        def forward(self, images):
            x = (images.permute(0, 3, 1, 2).float() - enet.INPUT_MEAN) / enet.INPUT_STD
            return enet.pool_features(self.folded(x), self.pooling)

    return DescriptorNet


def DescriptorNet(folded, pooling: enet.PoolingSpec):  # noqa: N802 - a class built lazily (torch import)
    """The export's torch module (see :func:`_make_descriptor_net_class`)."""
    global _DESCRIPTOR_NET
    if _DESCRIPTOR_NET is None:
        _DESCRIPTOR_NET = _make_descriptor_net_class()
    return _DESCRIPTOR_NET(folded, pooling)


_DESCRIPTOR_NET = None
