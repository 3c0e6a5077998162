"""Embedding models: what the detector needs of one, the backends that run them, their pool.

What the detector needs of one (``base``), the backends that load sentence-transformers,
ONNX or an OpenAI-compatible server (``embedders``, ``onnx_backend``) and the pool that
loads each once (``loading``)."""
