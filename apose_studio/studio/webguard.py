"""Who may drive the studio, and which files it may touch.

viser 1.1 accepts a websocket from any web page: a page on another site (or on another port of this
machine) that the user happens to visit could open `ws://127.0.0.1:8080` and press Open or Save. This
module closes that hole the way Jupyter does:

- **Origin check**: the websocket is accepted only from the studio's own page (same host and port;
  loopback names count as one host). Bound to loopback, the Host header must also name loopback, so a
  DNS-rebinding page (evil.example resolving to 127.0.0.1) is refused too. A *loopback name* is an IP
  literal in 127.0.0.0/8, `::1`, or exactly `localhost` (`is_loopback_name`): never a DNS name that
  merely starts with `127.` (`127.attacker.example`, `127.0.0.1.nip.io` can point anywhere).
- **Token**: the page and its websocket live under `/t/<token>/`, a secret made per start and printed
  by the command; without it, nothing but a "needs the token" page is served. On loopback too, as
  Jupyter does: any local process (another user's, a sandboxed app's) can forge an Origin header,
  but cannot guess 192 random bits. `--token` picks a fixed one (a bookmark, a scripted demo).
- **Workspace**: file paths typed into the page resolve inside a few root folders (`--root`).
- **Memory**: at most `MAX_CONNECTIONS` websockets at once (the next gets 503 with the reason), a
  message over `MAX_MESSAGE_BYTES` closes its connection from its header (viser's own limit is 50 MB;
  the page sends 512 KiB at most), `MAX_QUEUED_FRAMES` read ahead per connection; and no websocket until
  the studio is built (`ready`).

viser offers no hook for these, so `start_viser` wraps the request hook (and the size limits) of the
websockets server while viser starts it (the one place that touches viser's internals for this). What a
connected page sends is checked in viser_adapter.py.
"""

from __future__ import annotations

import hmac
import http
import ipaddress
import logging
import re
import secrets
import threading
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

from apose_studio.errors import AposeError
from apose_studio.safeio import check_path_text

_START_LOCK = threading.Lock()
log = logging.getLogger(__name__)


def is_loopback_name(name: str) -> bool:
    """True for an IP literal in 127.0.0.0/8 or ::1 (brackets allowed) and for exactly `localhost`
    (any case). Everything else is a name some DNS server answers for: `127.evil.example`,
    `127.0.0.1.nip.io`, `localhost.`, `localhost.evil.example`, `0x7f.1` and `2130706433` are not loopback."""
    name = (name or "").lower()
    if name == "localhost":
        return True
    if name.startswith("[") and name.endswith("]"):
        name = name[1:-1]
    try:
        address = ipaddress.ip_address(name)
    except ValueError:
        return False
    return address.is_loopback and (address.version == 4 or address == ipaddress.IPv6Address("::1"))


def is_loopback_bind(host: str) -> bool:
    return is_loopback_name(host)


# What a browser sends, and nothing else: a Host header is host[:port] and an Origin is
# scheme://host[:port] (RFC 6454's serialisation: no userinfo, path, backslash, whitespace, nor a port
# with a leading zero). Anything looser is refused before it is parsed, so no parser's leniency
# (urlsplit takes "evil@127.0.0.1" as 127.0.0.1) decides what counts as loopback.
_HOST = r"(?:\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9._-]+)"
_HOST_HEADER = re.compile(rf"{_HOST}(?::[0-9]{{1,5}})?")
_ORIGIN = re.compile(rf"https?://{_HOST}(?::[1-9][0-9]{{0,4}})?")


def _host_port(netloc: str, default_port: int | None) -> tuple[str, int | None]:
    """('127.0.0.1', 8080) from '127.0.0.1:8080'; IPv6 brackets removed; names lower-cased; ('', None)
    for anything that is not host[:port]."""
    if not _HOST_HEADER.fullmatch(netloc):
        return "", None
    parts = urlsplit("//" + netloc)
    try:
        port = parts.port
    except ValueError:
        return "", None
    return (parts.hostname or "").lower(), port if port is not None else default_port


def _has_token(path: str, token: str) -> bool:
    """`path` is /t/<token>, /t/<token>/… or /t/<token>?…; compared in constant time."""
    if not path.startswith("/t/"):
        return False
    rest = path[3:]
    end = min((i for i in (rest.find("/"), rest.find("?")) if i >= 0), default=len(rest))
    return hmac.compare_digest(rest[:end].encode("utf-8", "surrogateescape"), token.encode())


def refusal(*, path: str, host_header: str | None, origin: str | None, port: int, bound_loopback: bool,
            token: str | None, websocket: bool) -> str | None:
    """Why a request must be refused, or None to let it through (pure; the rules of the module doc)."""
    if token is not None and not _has_token(path, token):
        return "this studio needs its token: open the address that `apose studio` printed (it ends in /t/<token>/)"
    host, _ = _host_port(host_header or "", 80)  # the Host header's port is not checked: the socket's is
    if bound_loopback and not is_loopback_name(host):
        return f"refused: the studio listens on this machine only, and Host {host_header!r} is not a loopback name"
    if not websocket:
        return None
    if not origin:
        return "refused: a websocket without an Origin header (only the studio's own page may connect)"
    if not _ORIGIN.fullmatch(origin):
        return f"refused: Origin {origin!r} is not an origin a browser sends (scheme://host[:port])"
    o = urlsplit(origin)
    o_host, o_port = _host_port(o.netloc, {"http": 80, "https": 443}.get(o.scheme))
    same_host = o_host == host or (is_loopback_name(o_host) and is_loopback_name(host))
    if o.scheme not in ("http", "https") or not same_host or o_port != port:
        return f"refused: Origin {origin!r} is not the studio's own page"
    return None


def new_token() -> str:
    return secrets.token_urlsafe(24)


def check_token(token: str) -> str:
    """A chosen token, refused when it is guessable or does not fit in a URL path segment."""
    token = str(token)
    if len(token) < 16 or not all(c.isascii() and (c.isalnum() or c in "-_") for c in token):
        raise AposeError(f"--token: {len(token)} characters; use at least 16 of A-Z, a-z, 0-9, '-' and '_' "
                         "(or leave it out: each start then makes a new random one)")
    return token


MAX_MESSAGE_BYTES = 2**20  # what a page sends at most: an upload part is 512 KiB, everything else far less
MAX_QUEUED_FRAMES = 4  # frames a connection may have read but not yet handled (then TCP pushes back)
MAX_CONNECTIONS = 16  # websockets at once (tabs open, and handshakes under way)


def start_viser(host: str, port: int, token: str | None, label: str = "apose studio",
                ready: threading.Event | None = None):
    """A viser server whose websockets and page go through `refusal` first. A websocket is also refused
    (503, with the reason) until `ready` is set (the studio is still being built) and while
    `MAX_CONNECTIONS` are open; a message over `MAX_MESSAGE_BYTES` closes its connection (viser's own
    limit is 50 MB, and a half-sent 49 MB frame per tab held 4.75 GB in 60 tabs)."""
    import viser  # the studio's own dependency: loaded only when a studio starts
    import websockets.asyncio.server as wss  # viser's transport: loaded only when a studio starts
    from websockets.protocol import State  # viser's transport: loaded only when a studio starts

    original = wss.serve
    bound_loopback = is_loopback_bind(host)
    live: set = set()  # the websockets let through and not yet closed (only the server's event loop touches it)

    def serve(handler, *args, process_request=None, **kwargs):
        def guarded(connection, request):
            def one(name: str) -> str | None:  # a header sent twice counts as missing
                values = request.headers.get_all(name)
                return values[0] if len(values) == 1 else None

            # any request that asks for a websocket in any spelling ("Upgrade: , WebSocket", two Upgrade
            # headers, a Sec-WebSocket-Key alone) is checked as one: which of them a server would upgrade
            # is its parser's business, not this guard's
            upgrades = [t.strip().lower() for v in request.headers.get_all("Upgrade") for t in v.split(",")]
            websocket = "websocket" in upgrades or "Sec-WebSocket-Key" in request.headers
            reason = refusal(path=request.path, host_header=one("Host"), origin=one("Origin"),
                             port=connection.local_address[1], bound_loopback=bound_loopback, token=token,
                             websocket=websocket)
            if reason is not None:
                return connection.respond(http.HTTPStatus.FORBIDDEN, reason + "\n")
            if websocket:
                if ready is not None and not ready.is_set():
                    return connection.respond(http.HTTPStatus.SERVICE_UNAVAILABLE,
                                              "the studio is starting; the page connects again by itself\n")
                live.difference_update([c for c in live if c.state is State.CLOSED])
                if len(live) >= MAX_CONNECTIONS:
                    log.warning("refused a websocket: %d are open, the limit", len(live))
                    return connection.respond(http.HTTPStatus.SERVICE_UNAVAILABLE,
                                              f"the studio has {MAX_CONNECTIONS} tabs connected, its limit: close "
                                              "one, and this page connects by itself\n")
                live.add(connection)
            if token is not None and not websocket:  # the page lives under /t/<token>/
                from websockets.http11 import Request  # viser's transport: loaded only when a studio starts

                rest = request.path[len(f"/t/{token}"):] or "/"
                request = Request(rest, request.headers)
            return process_request(connection, request) if process_request is not None else None

        kwargs["max_size"] = MAX_MESSAGE_BYTES
        kwargs["max_queue"] = MAX_QUEUED_FRAMES
        return original(handler, *args, process_request=guarded, **kwargs)

    import rich  # viser's console: loaded only when a studio starts

    printer = rich.print
    with _START_LOCK:  # viser starts its server inside the constructor; only that call sees the wrapper
        wss.serve = serve
        rich.print = lambda *a, **k: None  # viser's banner shows the address without the token: `serve` prints ours
        try:
            return viser.ViserServer(host=host, port=port, label=label, verbose=False)
        finally:
            wss.serve = original
            rich.print = printer


def studio_url(host: str, port: int, token: str | None) -> str:
    shown = "127.0.0.1" if host in ("0.0.0.0", "::", "") else host
    return f"http://{shown}:{port}/" + (f"t/{token}/" if token else "")


# --------------------------------------------------------------------------------------- files


@dataclass(frozen=True)
class Workspace:
    """The folders whose files the studio's page may name. Paths typed into the page resolve here."""

    roots: tuple[Path, ...]
    trusted: tuple[Path, ...] = ()  # folders of the files named on the command line at start (their meshes)

    @classmethod
    def of(cls, *folders) -> "Workspace":
        return cls(tuple(dict.fromkeys(Path(f).expanduser().resolve() for f in folders if f is not None)))

    def trusting(self, *folders) -> "Workspace":
        """This workspace, also reading from `folders` (never writing there, nor resolving typed paths):
        the meshes of an assembly or dataset the user named on the command line, wherever they lie."""
        extra = (Path(f).resolve() for f in folders)
        return Workspace(self.roots, tuple(dict.fromkeys((*self.trusted, *extra))))

    @property
    def readable(self) -> tuple[Path, ...]:
        """Where the studio's page actions may read files (safeio.reads_within): the roots, the folders
        of the start-up files, and the package's own files."""
        return (*self.roots, *self.trusted, Path(__file__).resolve().parents[1])

    def check_assembly(self, asm) -> None:
        """Every mesh an assembly file names lies in the workspace (a file in it may name
        `../outside/secret.stl` or `/etc/...`); AposeError naming the file, the part and the mesh."""
        for pid, part in asm.parts.items():
            try:
                self.resolve(part.mesh, "mesh")
            except AposeError as e:
                where = f"{asm.path}: " if getattr(asm, "path", None) else ""
                raise AposeError(f"{where}parts.{pid}.mesh: {e}") from None

    def resolve(self, text: str | Path, what: str = "file") -> Path:
        """The absolute path, or an AposeError naming the workspace when it lies outside."""
        p = check_path_text(text, what).expanduser()
        if not p.is_absolute():
            p = self.roots[0] / p
        p = p.resolve()
        if not any(p == r or p.is_relative_to(r) for r in self.roots):
            where = ", ".join(str(r) for r in self.roots)
            raise AposeError(f"{p}: outside the studio's workspace ({where}); the studio reads and writes only "
                             f"there. Move the {what} in, or restart with --root covering it.")
        return p
