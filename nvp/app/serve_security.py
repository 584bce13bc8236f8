"""Which requests ``nvp serve`` answers at all: its local-app security model (``docs/serve.md``).

A web page on any site can make the user's browser send requests to ``127.0.0.1``, and can rebind its own
host name to ``127.0.0.1`` (DNS rebinding) to read the answers as if it were the app. Three checks, in
this order, stop that before a request reaches the app:

1. **Host**: the ``Host`` header must name the address the server listens on, ``localhost``,
   ``127.0.0.1`` or ``[::1]`` (a server bound to every interface also takes IP literals and this
   machine's names: a rebound host name is never an IP literal). Otherwise 421.
2. **Origin**: a request that says it comes from a page (``Origin``, ``Sec-Fetch-Site``) must come from
   this app's own origin. Otherwise 403.
3. **Token**: every ``/api/`` call carries the server's per-launch token (``X-NVP-Token`` header,
   ``Authorization: Bearer``, or ``?token=`` on GET/HEAD for ``<img>``/``<video>`` sources). Missing → 401,
   wrong → 403. A loopback server puts it in the page it serves; ``curl`` users read it from the start-up
   line or the ``serve-token`` file (mode 0600) in the data folder.

Every answer also carries headers that keep the page out of frames and other sites' pages
(:func:`security_headers`), and the page a nonce-based Content-Security-Policy (:func:`page_csp`).
"""

from __future__ import annotations

import hmac
import ipaddress
import os
import secrets
import socket
from dataclasses import dataclass
from email.message import Message
from http import HTTPStatus
from pathlib import Path

TOKEN_ENV = "NVP_SERVE_TOKEN"
"""Environment variable holding an explicit token (required for a ``--host`` other than loopback)."""
TOKEN_FILE = "serve-token"
"""The file in the data folder that holds the running server's token (mode 0600, removed at exit)."""
MIN_TOKEN_CHARS = 16
LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1"})


class ApiError(Exception):
    """A request refused with an HTTP status and a one-line message (sent as ``{"error": message}``)."""

    def __init__(self, status: HTTPStatus, message: str) -> None:
        super().__init__(message)
        self.status = status


def is_loopback(host: str) -> bool:
    """True for ``localhost`` and loopback IP addresses (reachable from this machine only)."""
    name = host.strip("[]").lower()
    if name == "localhost":
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


def split_host(value: str) -> tuple[str, str]:
    """``(name, port)`` of a Host header (``"[::1]:80"`` → ``("::1", "80")``); raises ValueError."""
    value = value.strip()
    if value.startswith("["):
        name, sep, rest = value[1:].partition("]")
        if not sep or (rest and not rest.startswith(":")):
            raise ValueError(value)
        port = rest[1:]
    elif value.count(":") == 1:
        name, port = value.split(":")
    else:
        name, port = value, ""
    if not name or any(c in name for c in "/\\@ \t?#") or (port and not (port.isdigit() and len(port) <= 5)):
        raise ValueError(value)
    return name.lower(), port


def new_token() -> str:
    return secrets.token_urlsafe(32)


def write_token_file(folder: Path, token: str) -> Path:
    """Write ``token`` to ``folder/serve-token``, readable by this user only (written whole, then renamed)."""
    path = folder / TOKEN_FILE
    tmp = folder / f".{TOKEN_FILE}.{os.getpid()}.tmp"
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(token + "\n")
    os.replace(tmp, path)
    return path


def remove_token_file(folder: Path, token: str) -> None:
    """Remove the token file if it still holds ``token`` (a newer server's file is left alone)."""
    path = folder / TOKEN_FILE
    try:
        if path.read_text().strip() == token:
            path.unlink()
    except OSError:
        pass


@dataclass(frozen=True)
class Guard:
    """The three checks of the module docstring for one server."""

    token: str
    """The per-launch token every ``/api/`` call must carry."""
    hosts: frozenset[str]
    """Host names (lower case, IPv6 without brackets) the server answers for."""
    any_ip: bool
    """Also answer for any IP literal (a server bound to every interface)."""
    embed_token: bool
    """Put the token in the page (loopback only: anyone who can load the page gets it)."""

    @classmethod
    def for_address(cls, host: str, token: str) -> Guard:
        name = host.strip("[]").lower()
        hosts = set(LOOPBACK_NAMES) | {name}
        wildcard = name in ("", "0.0.0.0", "::")
        if wildcard:
            for n in (socket.gethostname(), socket.getfqdn()):
                if n:
                    hosts.add(n.lower())
        return cls(token, frozenset(hosts), wildcard, is_loopback(host))

    def check_host(self, headers: Message) -> str:
        """The request's Host header value when the server answers for it; ApiError otherwise."""
        values = headers.get_all("Host") or []
        if len(values) != 1:
            raise ApiError(HTTPStatus.BAD_REQUEST, "send one Host header")
        try:
            name, _ = split_host(values[0])
        except ValueError:
            raise ApiError(HTTPStatus.BAD_REQUEST, "the Host header is not a host name") from None
        if name not in self.hosts and not (self.any_ip and _is_ip(name)):
            raise ApiError(
                HTTPStatus.MISDIRECTED_REQUEST,
                "this server answers requests for its own address and localhost only",
            )
        return values[0].strip()

    def check_origin(self, headers: Message, host: str, page: bool) -> None:
        """Refuse requests sent by another site's page. ``page``: a GET of the page itself, which may
        be opened from a link anywhere (it cannot be read cross-site, or framed)."""
        origins = headers.get_all("Origin") or []
        if len(origins) > 1:
            raise ApiError(HTTPStatus.FORBIDDEN, "send at most one Origin header")
        if origins:
            origin = origins[0].strip().lower()
            if origin not in (f"http://{host}".lower(), f"https://{host}".lower()):
                raise ApiError(HTTPStatus.FORBIDDEN, "requests from another site's page are refused")
        site = (headers.get("Sec-Fetch-Site") or "").strip().lower()
        if site in ("cross-site", "same-site") and not page:
            raise ApiError(HTTPStatus.FORBIDDEN, "requests from another site's page are refused")

    def check_token(self, headers: Message, query: dict[str, list[str]], method: str) -> None:
        given = (headers.get("X-NVP-Token") or "").strip()
        auth = (headers.get("Authorization") or "").strip()
        if not given and auth[:7].lower() == "bearer ":
            given = auth[7:].strip()
        if not given and method in ("GET", "HEAD") and query.get("token"):
            given = query["token"][0]
        if not given:
            raise ApiError(
                HTTPStatus.UNAUTHORIZED,
                "this API needs the server's token: send it as the X-NVP-Token header (it is on the "
                f"server's start-up line and in the file {TOKEN_FILE} in its data folder)",
            )
        if not hmac.compare_digest(given.encode("utf-8", "replace"), self.token.encode()):
            raise ApiError(HTTPStatus.FORBIDDEN, "wrong token (a token is valid while its server runs)")


def security_headers() -> dict[str, str]:
    """Headers sent with every answer: no sniffing, no framing, no referrer, not embeddable elsewhere."""
    return {
        "X-Content-Type-Options": "nosniff",
        "X-Frame-Options": "DENY",
        "Referrer-Policy": "no-referrer",
        "Cross-Origin-Resource-Policy": "same-origin",
        "Cross-Origin-Opener-Policy": "same-origin",
        "Cache-Control": "no-store",
        "Content-Security-Policy": "default-src 'none'; frame-ancestors 'none'; sandbox",
    }


def page_csp(nonce: str) -> str:
    """The page's policy: its own script and style (by nonce), media and API calls to itself only."""
    return (
        f"default-src 'none'; script-src 'nonce-{nonce}'; style-src 'nonce-{nonce}'; img-src 'self'; "
        "media-src 'self'; connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
    )
