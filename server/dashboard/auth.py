"""Who may open the dashboard: tokens, the sites each allows, the cookie, the WebSocket Origin check.

A token is given on the command line (``--http-token``, every site), in the settings file, or in a
tokens file (``--http-tokens FILE``: one ``token: site1,site2`` per line, ``token: *`` for every
site; ``#`` starts a comment). Opening ``/?token=TOKEN`` sets it as an ``HttpOnly; SameSite=Strict``
cookie and redirects to ``/`` (the token leaves the address bar and the history); every later
request, and the WebSocket handshake, carries the cookie. Scripts may send ``Authorization: Bearer
TOKEN`` instead. Tokens are compared in constant time (``hmac.compare_digest``).

CORS does not cover WebSockets (cross-site WebSocket hijacking): a handshake whose ``Origin`` is not
the page's own (scheme, host and port of the request) is refused; a handshake without an Origin is a
non-browser client and needs the token like any other.
"""

from __future__ import annotations

import hmac
import re
import secrets
from dataclasses import dataclass
from pathlib import Path

from hybridloc.errors import BadInput
from hybridloc.wire.protocol import check_id

COOKIE = "hybridloc_dashboard"
#: Shortest accepted token: 16 characters of a URL-safe alphabet (96 bits for a generated one).
MIN_TOKEN_CHARS = 16
_TOKEN = re.compile(r"^[A-Za-z0-9_.~\-]+$")


def new_token() -> str:
    """A random token (32 URL-safe characters, 192 bits)."""
    return secrets.token_urlsafe(24)


def check_token(token: str, where: str) -> str:
    if not _TOKEN.match(token or ""):
        raise BadInput(f"{where}: a token is letters, digits, '_', '.', '~' and '-' only")
    if len(token) < MIN_TOKEN_CHARS:
        raise BadInput(f"{where}: a token needs at least {MIN_TOKEN_CHARS} characters, got {len(token)}")
    return token


def read_tokens_file(path: str | Path) -> dict[str, frozenset[str] | None]:
    """{token: its sites (None: every site)} of a tokens file (lines ``token: site1,site2``)."""
    p = Path(path)
    if not p.is_file():
        raise BadInput(f"{p}: no such tokens file")
    out: dict[str, frozenset[str] | None] = {}
    for n, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        token, sep, rest = line.partition(":")
        where = f"{p}:{n}"
        if not sep:
            raise BadInput(f"{where}: expected 'token: site1,site2' (or 'token: *'), got {line!r}")
        token = check_token(token.strip(), where)
        names = [s.strip() for s in rest.split(",") if s.strip()]
        if not names:
            raise BadInput(f"{where}: no site after the token (use '*' for every site)")
        if names == ["*"]:
            sites = None
        else:
            try:
                sites = frozenset(check_id(s, "site") for s in names)
            except ValueError as exc:
                raise BadInput(f"{where}: {exc}") from None
        if token in out:
            raise BadInput(f"{where}: the token is listed twice")
        out[token] = sites
    if not out:
        raise BadInput(f"{p}: no token in the tokens file")
    return out


@dataclass(frozen=True)
class Access:
    """The tokens the dashboard accepts and the sites each may see (None: every site)."""

    tokens: dict[str, frozenset[str] | None]

    def __post_init__(self) -> None:
        if not self.tokens:
            raise ValueError("the dashboard needs at least one token")

    def sites_for(self, token: str | None) -> tuple[bool, frozenset[str] | None]:
        """(token valid, its sites)."""
        if not token:
            return False, None
        given = token.encode()
        found, sites = False, None
        for t, s in self.tokens.items():  # every token compared, in constant time each
            if hmac.compare_digest(t.encode(), given):
                found, sites = True, s
        return found, sites


def origin_allowed(origin: str | None, scheme: str, host: str | None, extra: tuple[str, ...] = ()) -> bool:
    """A WebSocket handshake's Origin: absent (not a browser), the page's own, or one configured."""
    if origin is None:
        return True
    if host and origin.lower() == f"{'https' if scheme in ('https', 'wss') else 'http'}://{host}".lower():
        return True
    return origin in extra
