"""One typed settings object for the server, the clients, the command line and the dashboard: site,
endpoint, database, security files, the local filter's tuning and the dashboard's page.

Read by :func:`load_settings` from a TOML file (``hybridloc --config FILE``, or the file named by
``HYBRIDLOC_CONFIG``) and from ``HYBRIDLOC_*`` environment variables. Precedence, highest first: a
command-line option, the environment, the file, the built-in default (the defaults are the command
line's own, so no file and no variable change nothing). Example file::

    site = "site1"
    endpoint = "tcp/10.0.0.5:7447"
    db = "postgresql+psycopg://hybridloc@db/hybridloc"
    floorplan = "sites/site1"          # the site's floor plans (client --floorplan)
    locate_workers = 1                 # serve: processes answering the stored scans (0: in the server)
    ingest_workers = 2                 # serve: processes storing the batches (0: in the server; default "auto")

    [security]
    user = "phone-7"
    tls_ca = "certs/ca.pem"

    [filter]
    kind = "particle"                  # kalman | particle | kourogi
    speed = 0                          # replay speed factor (0: as fast as possible)

    [http]                             # the operator dashboard (serve --http, hybridloc dashboard)
    listen = "127.0.0.1:8080"          # HOST:PORT of the page; off when not set
    token = "..."                      # the page's token (none: serve --http generates one)
    tokens_file = "dashboard-tokens"   # lines "token: site1,site2" ("token: *": every site)

    [slam]                             # the server's crowd-SLAM worker per served site
    enabled = true
    idle_s = 180                       # a walk silent this long (s) is finished
    batch_every = 25                   # a batch re-solve after this many new walks
    batch_share = 0.0                  # ... and this share of the walks the last batch solved
    interval_s = 3600                  # ... or this long after the last one (s)
    processes = 0                      # a batch's groups of floors side by side (0: the usable cores)
    grow_map = false                   # serve each added walk's labels on top of the map version

Environment variables are the keys in capitals, a section's keys prefixed by its name:
``HYBRIDLOC_SITE``, ``HYBRIDLOC_ENDPOINT``, ``HYBRIDLOC_SECURITY_PASSWORD``, ``HYBRIDLOC_FILTER_KIND``...
An unknown key (in the file or as a ``HYBRIDLOC_*`` variable) or a value of the wrong type is a
:class:`~hybridloc.errors.BadInput` that names the key.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import BadInput, DataFormatError, MissingData

ENV_PREFIX = "HYBRIDLOC_"
#: ``HYBRIDLOC_*`` variables that are not settings (the file's own name; the test suite's data folder)
ENV_NOT_SETTINGS = frozenset({"HYBRIDLOC_CONFIG", "HYBRIDLOC_SHARED_DATA"})

FILTER_KINDS = ("kalman", "particle", "kourogi")
LOCATE_METHODS = ("knn", "prob")


@dataclass(frozen=True)
class SecuritySettings:
    """Zenoh access control and TLS (the options of ``serve``, ``client`` and ``status``)."""

    user: str | None = None  # a client's user name
    password: str | None = None  # a client's password
    users: str | None = None  # server: the user:password dictionary file (enables authentication)
    acl_devices: str | None = None  # server: file of device ids, each limited to its own keys
    tls_cert: str | None = None  # server certificate (PEM)
    tls_key: str | None = None  # server private key (PEM)
    tls_ca: str | None = None  # the CA a client checks the server's certificate with (PEM)


@dataclass(frozen=True)
class FilterSettings:
    """A client's local fusion (``client --filter/--start/--floor/--speed``)."""

    kind: str = "kalman"  # one of FILTER_KINDS
    start: str | None = None  # known start "x,y,sigma" in the site frame, m
    floor: str | None = None  # floor at the start
    speed: float = 1.0  # replay speed factor K (0 = as fast as possible)


@dataclass(frozen=True)
class SlamSettings:
    """The server's crowd-SLAM worker (``serve --no-slam/--slam-idle/--slam-batch-every/--slam-batch-share/--slam-interval/--slam-processes/--slam-grow-map``)."""

    enabled: bool = True  # a worker for every --site
    idle_s: float = 180.0  # an open walk whose device sent nothing for this long, s, is finished
    batch_every: int = 25  # a batch re-solve after this many walks added since the last (0: not by count)
    batch_share: float = 0.0  # ... and at least this share of the walks the last batch solved (0: the count alone)
    interval_s: float = 3600.0  # ... or this long after the last one when walks were added, s (0: not by time)
    processes: int = 0  # a batch re-solve's connected groups of floors solved side by side in this many processes (0: the usable cores)
    grow_map: bool = False  # each added walk's labels served on top of the map version until a batch's version holds them


@dataclass(frozen=True)
class HttpSettings:
    """The operator dashboard (``serve --http``, ``dashboard``)."""

    listen: str | None = None  # HOST:PORT of the page; off when not set
    token: str | None = None  # a token for every site (none: generated and printed)
    tokens_file: str | None = None  # lines "token: site1,site2"
    stale_s: float = 10.0  # a device whose newest pose or fix is older than this, s, is drawn stale
    lost_s: float = 60.0  # ... and lost after this long, s


@dataclass(frozen=True)
class Settings:
    site: str | None = None  # the site a client reports to and the server serves
    endpoint: str = "tcp/127.0.0.1:7447"  # Zenoh endpoint: the server listens on it, clients connect to it
    db: str = "hybridloc.db"  # SQLite file or database URL (postgresql+psycopg://...)
    method: str = "knn"  # the server's locate method, one of LOCATE_METHODS
    locate_workers: int = 0  # worker processes answering the server's stored scans (0: its locate thread)
    # worker processes decoding and storing the server's batches (0: its ingest thread; "auto": 2 on 2 cores or more)
    ingest_workers: int | str = "auto"
    floorplan: str | None = None  # the site's floor plan folder (Indoor Location Competition layout)
    security: SecuritySettings = field(default_factory=SecuritySettings)
    filter: FilterSettings = field(default_factory=FilterSettings)
    slam: SlamSettings = field(default_factory=SlamSettings)
    http: HttpSettings = field(default_factory=HttpSettings)

    def get(self, dotted: str) -> Any:
        """``get("security.tls_ca")``: a setting by its dotted key."""
        obj: Any = self
        for part in dotted.split("."):
            obj = getattr(obj, part)
        return obj


_SECTIONS = {"security": SecuritySettings, "filter": FilterSettings, "slam": SlamSettings, "http": HttpSettings}
_CHOICES = {"method": LOCATE_METHODS, "filter.kind": FILTER_KINDS}


def _fields(cls) -> dict[str, Any]:
    return {f.name: f.type for f in dataclasses.fields(cls) if f.name not in _SECTIONS}


def _coerce(key: str, value: Any, typ: str, from_env: bool) -> Any:
    """``value`` as the field's type (annotations are strings here: ``str | None``, ``float``)."""
    if value is None:
        return None
    if typ == "int | str":  # a count or "auto" (ingest_workers)
        if value == "auto" or (isinstance(value, int) and not isinstance(value, bool) and value >= 0):
            return value
        if from_env and isinstance(value, str) and value.isdigit():
            return int(value)
        raise BadInput(f'setting {key}: expected a whole number >= 0 or "auto", got {value!r}')
    if "bool" in typ:
        if from_env and isinstance(value, str) and value.lower() in ("1", "true", "yes", "on", "0", "false", "no", "off"):
            return value.lower() in ("1", "true", "yes", "on")
        if not isinstance(value, bool):
            raise BadInput(f"setting {key}: expected true or false, got {value!r}")
        return value
    if "int" in typ:
        if from_env and isinstance(value, str):
            try:
                return int(value)
            except ValueError:
                raise BadInput(f"setting {key}: expected a whole number, got {value!r}") from None
        if isinstance(value, bool) or not isinstance(value, int):
            raise BadInput(f"setting {key}: expected a whole number, got {value!r}")
        return value
    if "float" in typ:
        if isinstance(value, bool):
            raise BadInput(f"setting {key}: expected a number, got {value!r}")
        if from_env and isinstance(value, str):
            try:
                return float(value)
            except ValueError:
                raise BadInput(f"setting {key}: expected a number, got {value!r}") from None
        if not isinstance(value, (int, float)):
            raise BadInput(f"setting {key}: expected a number, got {value!r}")
        return float(value)
    if not isinstance(value, str):
        raise BadInput(f"setting {key}: expected a string, got {value!r}")
    return value


def _check_choice(key: str, value: Any) -> None:
    choices = _CHOICES.get(key)
    if choices is not None and value is not None and value not in choices:
        raise BadInput(f"setting {key}: expected one of {', '.join(choices)}, got {value!r}")


def _flatten_file(data: Mapping[str, Any], source: str) -> dict[str, Any]:
    """{dotted key: value} of a parsed TOML document, every key checked against the dataclasses."""
    out: dict[str, Any] = {}
    top = _fields(Settings)
    for k, v in data.items():
        if k in _SECTIONS:
            if not isinstance(v, dict):
                raise BadInput(f"{source}: setting {k}: expected a [{k}] table")
            sec = _fields(_SECTIONS[k])
            for kk, vv in v.items():
                if kk not in sec:
                    raise BadInput(f"{source}: unknown setting {k}.{kk} (known in [{k}]: {', '.join(sec)})")
                out[f"{k}.{kk}"] = _coerce(f"{k}.{kk}", vv, sec[kk], False)
        elif k in top:
            out[k] = _coerce(k, v, top[k], False)
        else:
            raise BadInput(f"{source}: unknown setting {k} (known: {', '.join([*top, *_SECTIONS])})")
    return out


def _flatten_env(env: Mapping[str, str]) -> dict[str, Any]:
    names: dict[str, tuple[str, str]] = {}
    for k, t in _fields(Settings).items():
        names[ENV_PREFIX + k.upper()] = (k, t)
    for sec, cls in _SECTIONS.items():
        for k, t in _fields(cls).items():
            names[f"{ENV_PREFIX}{sec.upper()}_{k.upper()}"] = (f"{sec}.{k}", t)
    out: dict[str, Any] = {}
    for var, value in env.items():
        if not var.startswith(ENV_PREFIX) or var in ENV_NOT_SETTINGS:
            continue
        if var not in names:
            raise BadInput(f"unknown setting in the environment: {var} (known: {', '.join(sorted(names))})")
        key, typ = names[var]
        out[key] = _coerce(var, value, typ, True)
    return out


def read_settings_file(path: str | os.PathLike) -> dict[str, Any]:
    """{dotted key: value} of a TOML settings file; :class:`MissingData` for a missing, empty or
    folder path, :class:`DataFormatError` for a file that is not TOML."""
    import tomllib

    p = Path(path)
    if p.is_dir():
        raise MissingData(f"{p}: is a folder, expected a settings file (TOML)")
    if not p.exists():
        raise MissingData(f"{p}: no such settings file")
    raw = p.read_bytes()
    if not raw.strip():
        raise MissingData(f"{p}: empty settings file (TOML)")
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise DataFormatError(p, None, f"not a TOML settings file ({exc})") from None
    return _flatten_file(data, str(p))


def load_settings(config_file: str | os.PathLike | None = None, env: Mapping[str, str] | None = None) -> Settings:
    """The settings of a file (default: ``$HYBRIDLOC_CONFIG`` when set) overridden by the environment
    (``env``, default ``os.environ``); command-line options go over these (:func:`resolve`)."""
    env = os.environ if env is None else env
    if config_file is None:
        config_file = env.get("HYBRIDLOC_CONFIG") or None
    values = read_settings_file(config_file) if config_file is not None else {}
    values.update(_flatten_env(env))
    for k, v in values.items():
        _check_choice(k, v)
    top = {k: v for k, v in values.items() if "." not in k}
    sections = {s: cls(**{k.split(".", 1)[1]: v for k, v in values.items() if k.startswith(s + ".")}) for s, cls in _SECTIONS.items()}
    return Settings(**top, **sections)


def resolve(option: Any, settings: Settings, key: str) -> Any:
    """A command-line option's value when given (not None), else the setting ``key`` (dotted)."""
    return option if option is not None else settings.get(key)
