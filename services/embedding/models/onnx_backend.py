"""A sentence-transformers model run by ONNX Runtime, in float32 or with int8 weights.

``onnx:<model>`` (float32) or ``onnx-int8:<model>`` (weights quantized to int8, activations
quantized per call).

The model is exported from its local files (``resolve_model``: the bundled model, a
directory, the Hugging Face cache; nothing is downloaded) the first time it is asked
for, with ``torch.onnx.export`` (its TorchScript exporter: the newer one needs onnxscript,
which this project does not install; the tests check the export against torch on inputs of
other lengths), and the file is kept under ``export_dir`` (the service
passes ``<data_dir>/onnx``): later loads read it. The int8 file is made from the
float32 one with ONNX Runtime's dynamic quantization; it embeds one text per call, since
dynamic quantization scales a call's activations by their range and a text's vector
would otherwise depend on the texts batched with it. Tokenisation is the model's own
(its Hugging Face tokenizer, same truncation), pooling its own: mean over the tokens
(the only pooling supported; the model's ``1_Pooling/config.json`` says so), then L2
normalisation, as sentence-transformers does.

One thread per inference by default, as the torch backend (``torch_threads``): on the
2-core machine one observation's latency matters, not one batch's throughput.
"""

from __future__ import annotations

import json
import os
import re
import threading
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from .base import Embedder, EmbedderError
from .embedders import ModelSource, resolve_model

INPUTS = ("input_ids", "attention_mask", "token_type_ids")


def default_export_dir() -> Path:
    """Where a caller without a data directory (``aesop detector eval``) keeps exports."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "aesop" / "onnx"


class OnnxEmbedder(Embedder):
    def __init__(self, model: str, *, int8: bool, export_dir: Path, threads: int = 1,
                 hf_cache_dir: str | Path | None = None) -> None:
        self._source = resolve_model(model, hf_cache_dir=hf_cache_dir)
        self._int8 = int8
        self._max_length = _max_length(self._source.path)
        _check_pooling(self._source.path)
        path = exported(self._source, export_dir, int8=int8)
        try:
            import onnxruntime as ort
            from transformers import AutoTokenizer

            options = ort.SessionOptions()
            options.intra_op_num_threads = threads
            options.inter_op_num_threads = 1
            # idle pool threads sleep instead of spinning: on a 2-core robot computer a
            # spinning pool would take the control loop's core between verdicts
            options.add_session_config_entry("session.intra_op.allow_spinning", "0")
            options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
            self._session = ort.InferenceSession(str(path), options,
                                                 providers=["CPUExecutionProvider"])
            self._tokenizer = AutoTokenizer.from_pretrained(str(self._source.path),
                                                            local_files_only=True)
        except Exception as exc:  # a third-party loader's failure is a backend failure
            raise EmbedderError(f"could not load {path} with ONNX Runtime: "
                                f"{type(exc).__name__}: {exc}") from exc
        self._wanted = [i.name for i in self._session.get_inputs()]
        self._lock = threading.Lock()
        self._dim = int(self._encode(["dimension probe"]).shape[1])

    @property
    def name(self) -> str:
        return ("onnx-int8:" if self._int8 else "onnx:") + self._source.name

    @property
    def dim(self) -> int:
        return self._dim

    def _encode(self, batch: list[str]) -> np.ndarray:
        if self._int8 and len(batch) > 1:
            # dynamic quantization scales each call's activations by their range, the
            # other texts (and their padding) included: a text's int8 vector would depend
            # on its batch, and a nominal detection seen again would not match itself
            return np.concatenate([self._encode([text]) for text in batch])
        try:
            tokens = self._tokenizer(batch, padding=True, truncation=True,
                                     max_length=self._max_length, return_tensors="np")
            feed = {name: np.asarray(tokens[name], dtype=np.int64) for name in self._wanted}
            with self._lock:
                hidden = self._session.run(None, feed)[0]
        except Exception as exc:
            raise EmbedderError(f"{self.name} failed on a batch of {len(batch)}: "
                                f"{type(exc).__name__}: {exc}") from exc
        mask = np.asarray(tokens["attention_mask"], dtype=np.float32)[..., None]
        pooled = (hidden * mask).sum(axis=1) / np.maximum(mask.sum(axis=1), 1e-9)
        norms = np.linalg.norm(pooled, axis=1, keepdims=True)
        return np.ascontiguousarray(pooled / np.maximum(norms, 1e-12), dtype=np.float32)

    def __repr__(self) -> str:
        return f"OnnxEmbedder(name={self.name!r}, dim={self._dim})"


def exported(source: ModelSource, export_dir: Path, *, int8: bool) -> Path:
    """The model's ONNX file under ``export_dir``, exported (and quantized) if missing:
    written to a temporary name of this process's and renamed, so a file there is whole even
    when two processes export at once (replicas or tools starting together on a fresh cache)."""
    folder = export_dir / re.sub(r"[^A-Za-z0-9_.-]+", "--", source.name)
    # the int8 file's name says its recipe: a cache pins "onnx-int8:<model>", and a
    # machine that still holds an export of the first recipe (per tensor) must not use it
    fp32, quantized = folder / "model.onnx", folder / "model-int8-per-channel.onnx"
    if not fp32.exists():
        folder.mkdir(parents=True, exist_ok=True)
        _export(source.path, fp32)
    if int8 and not quantized.exists():
        from onnxruntime.quantization import QuantType, quantize_dynamic

        tmp = _temporary(quantized)
        # one scale per output channel, 7-bit weights: cosine to the float32 vectors
        # 0.993 mean / 0.989 worst on VTOL briefs, against 0.966 / 0.951 per tensor; the
        # reduced range keeps CPUs without VNNI from saturating their u8 x s8 products
        quantize_dynamic(str(fp32), str(tmp), weight_type=QuantType.QInt8, per_channel=True,
                         reduce_range=True)
        os.replace(tmp, quantized)
    return quantized if int8 else fp32


def _temporary(target: Path) -> Path:
    """This process's own name to write ``target`` under before the rename."""
    return target.with_name(f"{target.name}.{os.getpid()}.tmp")


def _export(path: Path, target: Path) -> None:
    import torch
    from transformers import AutoModel, AutoTokenizer

    model = AutoModel.from_pretrained(str(path), local_files_only=True).eval()
    tokenizer = AutoTokenizer.from_pretrained(str(path), local_files_only=True)
    sample = tokenizer(["a sample to trace", "and another"], padding=True, return_tensors="pt")
    names = [n for n in INPUTS if n in sample]

    class Hidden(torch.nn.Module):  # the token embeddings: pooling happens in numpy
        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(self, *inputs: Any) -> Any:
            return self.model(**dict(zip(names, inputs, strict=True))).last_hidden_state

    tmp = _temporary(target)
    axes = {n: {0: "batch", 1: "tokens"} for n in names} | {"hidden": {0: "batch", 1: "tokens"}}
    try:
        with torch.no_grad(), warnings.catch_warnings():
            # known and checked (tests/integration/test_embedders_real.py: the export's
            # vectors against torch's, batches and lengths unlike the sample's): the legacy
            # exporter on purpose (the new one needs onnxscript); the tracer's constants are
            # an encoder's (no padding past the mask, never causal); the indices of
            # aten::index are token positions, never negative
            warnings.filterwarnings("ignore", "You are using the legacy TorchScript",
                                    DeprecationWarning)
            warnings.filterwarnings("ignore", "The feature will be removed",
                                    DeprecationWarning)
            warnings.filterwarnings("ignore", "Converting a tensor to a Python boolean")
            warnings.filterwarnings("ignore", "Exporting aten::index operator",
                                    UserWarning)
            torch.onnx.export(Hidden(), tuple(sample[n] for n in names), str(tmp),
                              input_names=names, output_names=["hidden"], dynamic_axes=axes,
                              opset_version=17, dynamo=False)
    except Exception as exc:
        tmp.unlink(missing_ok=True)
        raise EmbedderError(f"could not export {path} to ONNX: {type(exc).__name__}: "
                            f"{exc}") from exc
    os.replace(tmp, target)


def _max_length(path: Path) -> int:
    config = path / "sentence_bert_config.json"
    if config.is_file():
        return int(json.loads(config.read_text()).get("max_seq_length", 512))
    return 512


def _check_pooling(path: Path) -> None:
    config = path / "1_Pooling" / "config.json"
    if config.is_file() and not json.loads(config.read_text()).get("pooling_mode_mean_tokens"):
        raise EmbedderError(f"{path}: the ONNX backend pools by the mean of the tokens, and "
                            "this model pools otherwise (1_Pooling/config.json)")
