"""Settings of the vector-cache service (``AESOP_EMBEDDING_*``, and the shared ``AESOP_*``)."""

from __future__ import annotations

import os
import socket
from pathlib import Path

from pydantic import AliasChoices, Field, SecretStr, field_validator
from pydantic_settings import SettingsConfigDict

from shared.settings import Group, ServiceSettings

from .detector.adapt import DEFAULT_WINDOW, Recalibrate

DEFAULT_MODEL = "sentence-transformers/all-MiniLM-L6-v2"
# the service's default: the same model run by ONNX Runtime in float32, exported once into
# <data_dir>/onnx: the torch vectors (cosine > 0.9999, the same AUROCs on every domain)
# and about twice as fast on the bus (docs/benchmarks.md)
SERVICE_MODEL = "onnx:" + DEFAULT_MODEL
DEFAULT_K = 5  # k of a cache created without one (1..1000)
VERDICT_NEIGHBORS = 3  # nearest experiences a verdict or a score names


class EmbeddingLimits(Group):
    """What one caller may ask for (``AESOP_EMBEDDING_LIMITS``); past a limit, a 4xx that
    names it."""

    max_items: int = Field(default=10_000, ge=1)  # per request that adds or calibrates
    max_score_items: int = Field(default=256, ge=1)  # texts or vectors per score request
    max_text_chars: int = Field(default=4_000, ge=1)
    # REST texts being scored or waiting, over all requests: past it, 429 (the bus's
    # observations are never refused, and go first: see batching.ComputeThread)
    max_pending_texts: int = Field(default=1024, ge=1)
    max_jobs: int = Field(default=8, ge=1)  # add jobs running at once (429 past it)
    # pending proposals (scenes the reasoner answered "continue" for) a cache keeps; past
    # it a new scene is not proposed (logged), a known one is still counted
    max_pending_proposals: int = Field(default=1_000, ge=0)
    # observations per second scored per robot (a burst of one second's worth); past it
    # refused before decoding, counted, and said in an alarm on the robot's event key
    robot_hz: float = Field(default=25.0, gt=0.0, le=10_000.0)
    max_robots: int = Field(default=256, ge=1)  # robots tracked at once by the bus worker


class EmbeddingTuning(Group):
    """How the work is cut and run (``AESOP_EMBEDDING_TUNING``): the defaults are the
    measured ones (docs/benchmarks.md)."""

    embed_batch_size: int = Field(default=64, ge=1)
    # a REST score request runs as chunks of this many texts, so a bus verdict waits for
    # at most one chunk, and a caller that leaves stops its request at the next chunk
    score_chunk: int = Field(default=16, ge=1)
    microbatch: bool = True  # coalesce concurrent score requests into one embedding call
    # how long a lone request waits for company; 0: none, yet requests that arrive while
    # a batch is being embedded still form the next batch
    microbatch_window_ms: float = Field(default=0.0, ge=0.0)
    microbatch_max: int = Field(default=64, ge=1)
    # save a cache's index file once this many experiences were added or deleted since
    # the last save (0: only on close); a restart loads it and catches up from the database
    index_save_changes: int = Field(default=50_000, ge=0)
    # torch intra-op threads; 0 keeps torch's default (one per core). One thread keeps a
    # single observation's embedding at ~15 ms on a busy machine, where a pool of
    # spinning threads stalled verdicts for 1-2 s (measured with `aesop bench bus`)
    torch_threads: int = Field(default=1, ge=0, le=256)
    # ONNX Runtime threads per inference (onnx: and onnx-int8: models). Its pool is told
    # not to spin, so a second thread costs nothing while idle; measured with
    # `aesop bench detector --only latency` and `aesop bench bus` (docs/benchmarks.md)
    onnx_threads: int = Field(default=1, ge=1, le=256)
    # observation texts whose vectors are kept (the most recent; 0: none): a text seen again
    # is scored without embedding it again (a camera's scene repeats frame after frame)
    text_memo: int = Field(default=4096, ge=0, le=1_000_000)
    # with a shared store: how often a replica compares the stored versions with its own
    # besides following the others' notices (the most a lost notice delays a change)
    follow_poll_s: float = Field(default=5.0, gt=0.0, le=3600.0)


class EmbeddingAdapt(Group):
    """Drift and re-learning (``AESOP_EMBEDDING_ADAPT``, docs/embedding.md): when a robot's
    verdicts flag more than the calibration allows, and what accepting reviewed scenes
    does to the calibration."""

    # after accepted scenes: "window" recalibrates split-conformal on the leave-one-out
    # scores of the last ``window`` accepted scenes (services/embedding/detector/adapt.py);
    # "stale" keeps the calibration, marked stale, until an operator recalibrates
    recalibrate: Recalibrate = "window"
    window: int = Field(default=DEFAULT_WINDOW, ge=1, le=100_000)
    # a robot's last drift_window verdicts are tested against 1 - alpha (binomial); below
    # drift_significance it is drifting (services/embedding/detector/drift.py)
    drift_window: int = Field(default=50, ge=5, le=10_000)
    drift_significance: float = Field(default=1e-7, gt=0.0, lt=0.5)


class EmbeddingSettings(ServiceSettings):
    model_config = SettingsConfigDict(env_prefix="AESOP_EMBEDDING_", extra="ignore",
                                      validate_by_name=True)

    port: int = Field(default=8001, ge=0, le=65535)
    model: str = SERVICE_MODEL  # default model of new caches
    # a model named by a directory must be in here (default: <data_dir>/models); names
    # (the bundled model, the Hugging Face cache, openai:<name>) are looked up as before
    model_dir: Path | None = None
    max_models: int = Field(default=4, ge=1)  # loaded at once; the least used goes first
    openai_base_url: str = "https://api.openai.com/v1"  # for models named "openai:<name>"
    openai_api_key: SecretStr | None = Field(default=None, validation_alias=AliasChoices(
        "AESOP_EMBEDDING_OPENAI_API_KEY", "OPENAI_API_KEY"))
    detector_cache: str = "default"  # the cache the Zenoh worker scores observations against
    zenoh_worker: bool = True
    max_body_bytes: int = Field(default=64 * 1024 * 1024, ge=1024)
    # the most the database file may grow to (0: no limit but the disk's); a write past
    # it is answered 507 and nothing of it is stored, as on a full disk
    max_db_bytes: int = Field(default=0, ge=0)
    fsync: bool = True
    # the durable record: unset, the SQLite file in data_dir (one replica); a PostgreSQL
    # URL (postgresql://user:password@host:port/database) shared by detector replicas,
    # each with its own data_dir for its index files (docs/embedding.md)
    store: SecretStr | None = None
    # this replica's name among detector replicas (one Zenoh key chunk): robots are shared
    # among the live ones by rendezvous hashing (docs/embedding.md); default <host>-<pid>
    replica: str = ""
    limits: EmbeddingLimits = EmbeddingLimits()
    tuning: EmbeddingTuning = EmbeddingTuning()
    adapt: EmbeddingAdapt = EmbeddingAdapt()

    def replica_name(self) -> str:
        return self.replica or f"{socket.gethostname()}-{os.getpid()}"

    @field_validator("replica")
    @classmethod
    def _one_chunk(cls, v: str) -> str:
        if any(c in v for c in "/*$#? "):
            raise ValueError("AESOP_EMBEDDING_REPLICA is one Zenoh key chunk: no '/', '*', "
                             "'$', '#', '?' or spaces")
        return v

    @field_validator("store")
    @classmethod
    def _postgresql(cls, v: SecretStr | None) -> SecretStr | None:
        if v is None or not v.get_secret_value():
            return None
        if not v.get_secret_value().startswith(("postgresql://", "postgres://")):
            raise ValueError("AESOP_EMBEDDING_STORE is a PostgreSQL URL, postgresql://..."
                             " (unset: the SQLite file in the data directory)")
        return v
