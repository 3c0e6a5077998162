"""Settings of the vector-cache service (``AESOP_EMBEDDING_*``, and the shared ``AESOP_*``)."""

from __future__ import annotations

import os
import socket
from pathlib import Path

from pydantic import AliasChoices, Field, SecretStr, field_validator
from pydantic_settings import SettingsConfigDict

from shared.settings import BODY_LIMIT, Group, ServiceSettings

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

    max_items: int = Field(default=10_000, ge=1,
                           description="items per add or calibration request, 413")
    max_score_items: int = Field(default=256, ge=1,
                                 description="texts or vectors per score request, 413")
    max_text_chars: int = Field(default=4_000, ge=1, description="characters per text, 422")
    # (see batching.ComputeThread)
    max_pending_texts: int = Field(
        default=1024, ge=1,
        description="REST texts scoring or waiting, over all requests, 429; the bus's "
                    "observations are never refused, and go first")
    max_jobs: int = Field(default=8, ge=1, description="add jobs at once, 429")
    max_pending_proposals: int = Field(
        default=1_000, ge=0,
        description="pending proposals, scenes the reasoner answered continue for, a cache "
                    "keeps; past it a new scene is not proposed (logged), a known one still "
                    "counted")
    robot_hz: float = Field(
        default=25.0, gt=0.0, le=10_000.0,
        description="observations a second scored per robot, a second's burst; past it "
                    "refused before decoding, counted, and said in an alarm on the robot's "
                    "event key")
    max_robots: int = Field(default=256, ge=1,
                            description="robots the bus worker tracks at once")


class EmbeddingTuning(Group):
    """How the work is cut and run (``AESOP_EMBEDDING_TUNING``): the defaults are the
    measured ones (docs/benchmarks.md)."""

    embed_batch_size: int = Field(default=64, ge=1, description="texts per embedding call")
    score_chunk: int = Field(
        default=16, ge=1,
        description="texts per compute job of a REST request: a bus verdict waits for at "
                    "most one chunk, and a caller that leaves stops its request at the next")
    microbatch: bool = Field(default=True,
                             description="coalesce concurrent scoring into one embedding call")
    microbatch_window_ms: float = Field(
        default=0.0, ge=0.0,
        description="how long a lone request waits for company; 0: not at all, yet requests "
                    "that arrive while a batch is embedded still form the next batch")
    microbatch_max: int = Field(default=64, ge=1, description="most texts per batch")
    index_save_changes: int = Field(
        default=50_000, ge=0,
        description="save a cache's index file after this many changes, 0: only on close; "
                    "a restart loads it and catches up from the database")
    # measured with `aesop bench bus`
    torch_threads: int = Field(
        default=1, ge=0, le=256,
        description="torch intra-op threads, 0: torch's default (one per core); one keeps "
                    "an observation's embedding at ~15 ms on a busy machine, where a pool of "
                    "spinning threads stalled verdicts for 1-2 s")
    # measured with `aesop bench detector --only latency` and `aesop bench bus`
    onnx_threads: int = Field(
        default=1, ge=1, le=256,
        description="ONNX Runtime threads per inference of `onnx:` and `onnx-int8:` models; "
                    "the pool does not spin, so another thread costs nothing while idle")
    text_memo: int = Field(
        default=4096, ge=0, le=1_000_000,
        description="observation texts whose vectors are kept, the most recent (0: none): "
                    "one seen again, as a camera's scene repeats frame after frame, is not "
                    "embedded again")
    follow_poll_s: float = Field(
        default=5.0, gt=0.0, le=3600.0,
        description="with a shared store, how often (s) the stored versions are compared "
                    "besides the notices: the most a lost notice delays a change")


class EmbeddingAdapt(Group):
    """Drift and re-learning (``AESOP_EMBEDDING_ADAPT``, docs/embedding.md): when a robot's
    verdicts flag more than the calibration allows, and what accepting reviewed scenes
    does to the calibration."""

    # services/embedding/detector/adapt.py
    recalibrate: Recalibrate = Field(
        default="window",
        description="after accepted scenes: `window` recalibrates split-conformal on the "
                    "leave-one-out scores of the last `window` accepted ones; `stale` keeps "
                    "the calibration, marked stale, until an operator recalibrates")
    window: int = Field(default=DEFAULT_WINDOW, ge=1, le=100_000,
                        description="the accepted scenes a `window` recalibration uses")
    # services/embedding/detector/drift.py
    drift_window: int = Field(
        default=50, ge=5, le=10_000,
        description="a robot's last verdicts, tested against 1 - alpha by a binomial test")
    drift_significance: float = Field(
        default=1e-7, gt=0.0, lt=0.5,
        description="the binomial tail below which a robot is drifting")


class EmbeddingSettings(ServiceSettings):
    model_config = SettingsConfigDict(env_prefix="AESOP_EMBEDDING_", extra="ignore",
                                      validate_by_name=True)

    port: int = Field(default=8001, ge=0, le=65535, description="HTTP port")
    model: str = Field(
        default=SERVICE_MODEL,
        description="the model of new caches: a name, a path, `openai:<model>`, "
                    "`onnx:<model>` or `onnx-int8:<model>` (the default: the bundled model "
                    "run by ONNX Runtime in float32, exported on first use)")
    model_dir: Path | None = Field(
        default=None,
        description="where a model named by a directory must be (none: "
                    "`<data-dir>/models`); names (the bundled model, the Hugging Face "
                    "cache, `openai:<name>`) are looked up elsewhere")
    max_models: int = Field(default=4, ge=1,
                            description="models loaded at once (the least recently used let "
                                        "go)")
    openai_base_url: str = Field(default="https://api.openai.com/v1",
                                 description="server for `openai:` models")
    openai_api_key: SecretStr | None = Field(
        default=None,
        validation_alias=AliasChoices("AESOP_EMBEDDING_OPENAI_API_KEY", "OPENAI_API_KEY"),
        description="key for `openai:` models")
    detector_cache: str = Field(default="default",
                                description="the cache the Zenoh worker scores observations "
                                            "against")
    zenoh_worker: bool = Field(default=True,
                               description="run that worker (the detector on the bus)")
    max_body_bytes: int = Field(default=64 * 1024 * 1024, ge=1024, description=BODY_LIMIT)
    max_db_bytes: int = Field(
        default=0, ge=0,
        description="the most the database may grow to (0: the disk's size); a write past "
                    "it is answered 507 and nothing of it is stored, as on a full disk")
    fsync: bool = Field(default=True,
                        description="SQLite `synchronous=FULL` (else `OFF`) and fsync of "
                                    "index files")
    # docs/embedding.md
    store: SecretStr | None = Field(
        default=None,
        description="the durable record: unset, the SQLite file in `<data-dir>` (one "
                    "replica); a PostgreSQL URL, `postgresql://user:password@host:port/"
                    "database` (a secret: never echoed), one database shared by detector "
                    "replicas, each with its own data directory for its index files "
                    "(section 9)")
    replica: str = Field(
        default="",
        description="this replica's name among the detector replicas (one Zenoh key "
                    "chunk): its token `aesop/health/embedding/<name>`; robots are shared "
                    "among the live ones by rendezvous hashing (empty: `<host>-<pid>`)")
    limits: EmbeddingLimits = Field(
        default=EmbeddingLimits(),
        description="what one caller may ask for; past a limit, a 4xx that names it")
    tuning: EmbeddingTuning = Field(
        default=EmbeddingTuning(),
        description="how the work is cut and run; the defaults are the measured ones")
    adapt: EmbeddingAdapt = Field(default=EmbeddingAdapt(),
                                  description="drift and re-learning (section 1a)")

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
