"""Settings from ``AESOP_*`` variables: ``BusSettings``, ``ServiceSettings``, exposure checks.

What every service shares has a plain ``AESOP_`` name: the robot, the Zenoh
endpoints, the admin token, the data directory and the log level
(``AESOP_ROBOT``, ``AESOP_ZENOH_CONNECT``, ``AESOP_ADMIN_TOKEN``, ...). The rest
belongs to one service and carries its name: ``AESOP_EMBEDDING_*``,
``AESOP_REASONER_*``, ``AESOP_CONTROL_*``, ``AESOP_DASHBOARD_*`` (a service
subclasses ``ServiceSettings`` with its own ``env_prefix``; the shared fields
name their variable themselves, so the prefix does not touch them).

Build settings once at the edge (the CLI) and pass them down; logic never reads
``os.environ``. :func:`to_env` writes a settings object back as the
environment a child process reads it from (``aesop up``), so a bad value fails
where the plan is made, naming the field. Lists (Zenoh endpoints) are
comma-separated, e.g. ``AESOP_ZENOH_CONNECT=tcp/127.0.0.1:7447,tcp/10.0.0.2:7447``;
tuples and mappings are JSON.

A service's tuning knobs are grouped in nested settings (:class:`Group`), one variable
each: ``AESOP_EMBEDDING_LIMITS='{"max_jobs": 4}'`` as JSON, or one field at a time with
``__``, ``AESOP_EMBEDDING_LIMITS__MAX_JOBS=4``. A field the group does not have is an
error naming it.
"""

from __future__ import annotations

import difflib
import ipaddress
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

from pydantic import (
    AliasChoices,
    BaseModel,
    ConfigDict,
    Field,
    SecretStr,
    field_validator,
    model_validator,
)
from pydantic_settings import BaseSettings, EnvSettingsSource, NoDecode, SettingsConfigDict

Endpoints = Annotated[list[str], NoDecode]
S = TypeVar("S", bound=BaseSettings)


def _split(value: object) -> object:
    if isinstance(value, str):
        return [part.strip() for part in value.split(",") if part.strip()]
    return value


def shared(name: str) -> str:
    """The environment variable of a setting every service shares: ``AESOP_<NAME>``."""
    return f"AESOP_{name.upper()}"


class Group(BaseModel):
    """A group of a service's tuning knobs, read from one variable (see the module)."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class BusSettings(BaseSettings):
    """How a process joins the Zenoh network (defaults: a peer on loopback, no multicast)."""

    model_config = SettingsConfigDict(env_prefix="AESOP_", extra="ignore", validate_by_name=True,
                                      env_nested_delimiter="__")

    robot: str = Field(default="robot0", pattern=r"^[A-Za-z0-9_\-]+$",
                       validation_alias=shared("robot"),
                       description="the robot that control and the dashboard follow; the "
                                   "workers answer any robot")
    zenoh_mode: Literal["peer", "client"] = Field(default="peer",
                                                  validation_alias=shared("zenoh_mode"),
                                                  description="`peer` or `client`")
    zenoh_listen: Endpoints = Field(
        default_factory=list, validation_alias=shared("zenoh_listen"),
        description="endpoints to listen on, e.g. `tcp/127.0.0.1:7447`; a peer with neither "
                    "a listen endpoint nor a config file listens on `tcp/127.0.0.1:0`")
    zenoh_connect: Endpoints = Field(default_factory=list,
                                     validation_alias=shared("zenoh_connect"),
                                     description="endpoints to connect to, e.g. "
                                                 "`tcp/127.0.0.1:7447`")
    zenoh_multicast: bool = Field(default=False, validation_alias=shared("zenoh_multicast"),
                                  description="multicast scouting")
    zenoh_id: str | None = Field(
        default=None, pattern=r"^[0-9a-f]{1,32}$", validation_alias=shared("zenoh_id"),
        description="the session's Zenoh ID (hex, up to 32 digits), which names it in the "
                    "router's log; a router takes one session per ID, so every process its "
                    "own (none: random)")
    zenoh_config: Path | None = Field(
        default=None, validation_alias=shared("zenoh_config"),
        description="Zenoh JSON5 file, applied first; only settings set explicitly override it")
    zenoh_user: str | None = Field(
        default=None, min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_\-]+$",
        validation_alias=shared("zenoh_user"),
        description="the session's user at the router, whose dictionary must list it (needs "
                    "`AESOP_ZENOH_PASSWORD` or `AESOP_ZENOH_PASSWORD_FILE`)")
    zenoh_password: SecretStr | None = Field(
        default=None, validation_alias=shared("zenoh_password"),
        description="the session's password at the router (needs `AESOP_ZENOH_USER`)")
    zenoh_password_file: Path | None = Field(
        default=None, validation_alias=shared("zenoh_password_file"),
        description="the password from a file instead (a secret mounted by compose)")
    zenoh_tls_ca: Path | None = Field(
        default=None, validation_alias=shared("zenoh_tls_ca"),
        description="mutual TLS on `tls/` endpoints (a link that leaves the host): the CA "
                    "the router's certificate must chain to")
    zenoh_tls_cert: Path | None = Field(
        default=None, validation_alias=shared("zenoh_tls_cert"),
        description="this session's certificate (`aesop zenoh certs`): its common name is "
                    "its subject at the router's access-control list (needs "
                    "`AESOP_ZENOH_TLS_CA` and `AESOP_ZENOH_TLS_KEY`)")
    zenoh_tls_key: Path | None = Field(
        default=None, validation_alias=shared("zenoh_tls_key"),
        description="this session's certificate's key (needs `AESOP_ZENOH_TLS_CERT`)")

    _split_listen = field_validator("zenoh_listen", "zenoh_connect", mode="before")(_split)

    @model_validator(mode="after")
    def _credentials(self) -> BusSettings:
        has_password = self.zenoh_password is not None or self.zenoh_password_file is not None
        if has_password and self.zenoh_user is None:
            raise ValueError("AESOP_ZENOH_PASSWORD(_FILE) needs AESOP_ZENOH_USER")
        if self.zenoh_user is not None and not has_password:
            raise ValueError("AESOP_ZENOH_USER needs AESOP_ZENOH_PASSWORD or "
                             "AESOP_ZENOH_PASSWORD_FILE")
        if (self.zenoh_tls_cert is None) != (self.zenoh_tls_key is None):
            raise ValueError("AESOP_ZENOH_TLS_CERT and AESOP_ZENOH_TLS_KEY go together")
        if self.zenoh_tls_cert is not None and self.zenoh_tls_ca is None:
            raise ValueError("AESOP_ZENOH_TLS_CERT needs AESOP_ZENOH_TLS_CA (the CA the "
                             "router's certificate chains to)")
        return self

    def zenoh_tls(self) -> dict[str, Any] | None:
        """Zenoh's ``transport/link/tls`` block for these settings (None: no TLS), each
        file checked readable first, so a missing one is named here rather than by a TLS
        handshake that fails."""
        if self.zenoh_tls_ca is None:
            return None
        files = {"root_ca_certificate": ("AESOP_ZENOH_TLS_CA", self.zenoh_tls_ca)}
        if self.zenoh_tls_cert is not None and self.zenoh_tls_key is not None:
            files |= {"connect_certificate": ("AESOP_ZENOH_TLS_CERT", self.zenoh_tls_cert),
                      "connect_private_key": ("AESOP_ZENOH_TLS_KEY", self.zenoh_tls_key)}
        for variable, path in files.values():
            try:
                with open(path, "rb"):
                    pass
            except OSError as exc:
                raise ValueError(f"{variable}: cannot read {path}: {exc.strerror}") from None
        block: dict[str, Any] = {key: str(path) for key, (_, path) in files.items()}
        if self.zenoh_tls_cert is not None:
            block["enable_mtls"] = True
        return block

    def zenoh_secret(self) -> str | None:
        """The password to the router: the variable, else the file's first line."""
        if self.zenoh_password is not None:
            return self.zenoh_password.get_secret_value()
        if self.zenoh_password_file is not None:
            try:
                return self.zenoh_password_file.read_text().strip()
            except OSError as exc:
                raise ValueError(f"AESOP_ZENOH_PASSWORD_FILE: cannot read "
                                 f"{self.zenoh_password_file}: {exc.strerror}") from None
        return None


BODY_LIMIT = "request body limit, counted as the body streams in (413 past it)"


class ServiceSettings(BusSettings):
    """A service: the Zenoh bus plus an HTTP admin API and a data directory. ``host`` and
    ``port`` are the service's own (``AESOP_<SERVICE>_HOST``, ``_PORT``)."""

    host: str = Field(default="127.0.0.1",
                      description="bind address; an address off loopback needs a token")
    port: int = Field(default=8000, ge=0, le=65535, description="HTTP port")
    admin_token: SecretStr | None = Field(
        default=None, validation_alias=shared("admin_token"),
        description="bearer token, at least 16 characters (empty: none)")
    admin_token_file: Path | None = Field(
        default=None, validation_alias=shared("admin_token_file"),
        description="the token's first line from a file instead (a compose secret: not in "
                    "`docker inspect`)")
    data_dir: Path = Field(default=Path("data"), validation_alias=shared("data_dir"),
                           description="data directory; only embedding stores anything")
    log_level: Literal["debug", "info", "warning", "error"] = Field(
        default="info", validation_alias=shared("log_level"),
        description="`debug`, `info`, `warning` or `error`")
    # the CLI reads it first (shared.logs)
    log_format: Literal["text", "json"] = Field(
        default="text", validation_alias=shared("log_format"),
        description="`text` (time, level, logger, message), or `json`: one object per line "
                    "(`time` UTC ISO 8601, `level`, `logger`, `message`, `pid`, `exception`) "
                    "for a log collector; uvicorn's lines too (`shared/logs.py`)")
    max_body_bytes: int = Field(default=1024 * 1024, ge=1024, description=BODY_LIMIT)

    @field_validator("admin_token", mode="before")
    @classmethod
    def _empty_token_is_none(cls, v: object) -> object:
        return None if v in ("", None) else v

    @model_validator(mode="before")
    @classmethod
    def _token_from_file(cls, data: Any) -> Any:
        # the sources give a field by its name (init, read_settings) or its variable (env)
        if not isinstance(data, dict):
            return data
        file_keys = [k for k in ("admin_token_file", "AESOP_ADMIN_TOKEN_FILE")
                     if data.get(k) not in (None, "")]
        if not file_keys:
            return data
        if any(data.get(k) not in (None, "") for k in ("admin_token", "AESOP_ADMIN_TOKEN")):
            raise ValueError("set AESOP_ADMIN_TOKEN or AESOP_ADMIN_TOKEN_FILE, not both")
        file = Path(data[file_keys[0]])
        try:
            line = file.read_text().strip()
        except OSError as exc:
            raise ValueError(f"AESOP_ADMIN_TOKEN_FILE: cannot read {file}: "
                             f"{exc.strerror}") from None
        if not line:
            raise ValueError(f"AESOP_ADMIN_TOKEN_FILE: {file} is empty")
        return {**data, "admin_token": line}

    @field_validator("admin_token")
    @classmethod
    def _token_strength(cls, v: SecretStr | None) -> SecretStr | None:
        if v is not None and len(v.get_secret_value()) < 16:
            raise ValueError("AESOP_ADMIN_TOKEN must be at least 16 characters")
        return v

    def check_exposure(self) -> None:
        """Refuse to serve mutating routes off-loopback without a token."""
        if self.admin_token is None and not is_loopback(self.host):
            raise ValueError(
                f"refusing to listen on {self.host!r} without AESOP_ADMIN_TOKEN: "
                "set a token or bind to 127.0.0.1"
            )


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def env_names(cls: type[BaseSettings], name: str) -> tuple[str, ...]:
    """The environment variables field ``name`` of ``cls`` is read from, first one first."""
    info = cls.model_fields[name]
    alias = info.validation_alias
    if isinstance(alias, str):
        return (alias,)
    if isinstance(alias, AliasChoices):
        return tuple(str(choice) for choice in alias.choices)
    return (f"{cls.model_config.get('env_prefix', '')}{name}".upper(),)


def knob(cls: type[BaseSettings], group: str, name: str) -> str:
    """The variable that sets field ``name`` of ``cls``'s group ``group`` on its own
    (``AESOP_EMBEDDING_LIMITS__MAX_JOBS``), for messages that name a limit."""
    return f"{env_names(cls, group)[0]}__{name.upper()}"


def _group_names(cls: type[BaseSettings], name: str) -> tuple[str, ...]:
    annotation = cls.model_fields[name].annotation
    if isinstance(annotation, type) and issubclass(annotation, Group):
        return tuple(knob(cls, name, sub) for sub in annotation.model_fields)
    return ()


def to_env(settings: BaseSettings) -> dict[str, str]:
    """``settings`` as the environment its class reads it back from (fields that are None
    are left out: their default is None)."""
    out: dict[str, str] = {}
    for name in type(settings).model_fields:
        value = getattr(settings, name)
        if value is not None:
            out[env_names(type(settings), name)[0]] = _env_value(value)
    return out


def _env_value(value: Any) -> str:
    if isinstance(value, SecretStr):
        return value.get_secret_value()
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str | int | float | Path):
        return str(value)
    if isinstance(value, list):  # endpoint lists: comma-separated (NoDecode)
        return ",".join(str(v) for v in value)
    if isinstance(value, BaseModel):  # a group of knobs
        return value.model_dump_json()
    return json.dumps(value)  # tuples and mappings


def read_settings(cls: type[S], environ: Mapping[str, str], *,
                  defaults: Mapping[str, Any] | None = None, **forced: Any) -> S:
    """``cls`` as a process with environment ``environ`` would read it (pure: the
    process's own environment is not looked at). ``defaults`` apply where ``environ``
    says nothing; ``forced`` wins over both. A bad value raises ``ValidationError``
    naming the field."""
    raw = _MappingSource(cls, environ)()
    given: dict[str, Any] = {}
    for name in cls.model_fields:
        key = next((k for k in (name, *env_names(cls, name)) if k in raw), None)
        if key is not None:
            given[name] = raw[key]
    return cls.model_validate({**(defaults or {}), **given, **forced})


class _MappingSource(EnvSettingsSource):
    """pydantic-settings' environment source, over a given mapping."""

    def __init__(self, settings_cls: type[BaseSettings], environ: Mapping[str, str]) -> None:
        self._given = dict(environ)
        super().__init__(settings_cls)

    def _load_env_vars(self) -> Mapping[str, str | None]:
        if self.case_sensitive:
            return dict(self._given)
        return {name.lower(): value for name, value in self._given.items()}


def unknown_names(environ: Mapping[str, str], classes: Sequence[type[BaseSettings]]
                  ) -> dict[str, str | None]:
    """The ``AESOP_*`` variables of ``environ`` that none of ``classes`` reads, each with
    the name it most likely meant (``AESOP_LLM_MODEL`` -> ``AESOP_REASONER_LLM_MODEL``)."""
    knobs = [n for cls in classes for name in cls.model_fields for n in _group_names(cls, name)]
    known = {n for cls in classes for name in cls.model_fields for n in env_names(cls, name)}
    known.update(knobs)
    out: dict[str, str | None] = {}
    for name in sorted(environ):
        if not name.startswith("AESOP_") or name in known:
            continue
        tail = name.removeprefix("AESOP_")
        same = sorted(k for k in known if k.endswith(f"_{tail}"))
        close = difflib.get_close_matches(name, sorted(known), n=1)
        out[name] = _moved(name, knobs) or (
            same[0] if len(same) == 1 else (close[0] if close else None))
    return out


def _moved(name: str, knobs: Sequence[str]) -> str | None:
    """The group knob a flat name of the same service meant: ``AESOP_EMBEDDING_MAX_JOBS``
    (or ``AESOP_SIM_STATE_RATE_HZ``) -> ``AESOP_EMBEDDING_LIMITS__MAX_JOBS`` (the
    knob whose own name ends ``name`` the longest way)."""
    if "__" in name:
        return None
    fits = [(len(sub), knob) for knob in knobs
            for group, _, sub in (knob.rpartition("__"),)
            if name.endswith(f"_{sub}") and name.startswith(group.rsplit("_", 1)[0] + "_")]
    return max(fits)[1] if fits else None
