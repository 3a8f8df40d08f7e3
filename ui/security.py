"""What a shared studio must not do: serve uploads as live pages, or let passwords be guessed fast.

* `FileHeaders`: every `/file=` response gets `X-Content-Type-Options: nosniff`, and a file from any
  folder whose type could run script in the browser (HTML, SVG and every other XML type, JS, CSS,
  PDF, ...) is sent as a download (`Content-Disposition: attachment`, `application/octet-stream`),
  never inline. (Gradio itself does this for the upload folder, not for `allowed_paths`; this holds
  for both.)
* `LoginGuard`: the `auth` callable given to Gradio. Each client (its address) that fails to log
  in waits before its next attempt, twice as long after every failure in a row (0.5 s, 1 s, 2 s,
  … up to 30 s); attempts from one client are taken one at a time, so guessing in parallel does
  not help. Every failure is logged with the user name and the client's address.
"""

from __future__ import annotations

import asyncio
import contextvars
import hmac
import logging
import time
from dataclasses import dataclass, field

log = logging.getLogger("unirelight.studio.auth")

BACKOFF_BASE_S = 0.5  # wait after the first failure; doubles with each further failure
BACKOFF_MAX_S = 30.0
FORGET_AFTER_S = 3600.0  # a client's failures are forgotten after this long without attempts
MAX_CLIENTS = 10_000  # bound on remembered clients (oldest forgotten first)

_now = time.monotonic  # the clock and the wait, as module attributes so tests can drive them
_sleep = asyncio.sleep

_client: contextvars.ContextVar[str] = contextvars.ContextVar("login_client", default="unknown")

# Types a browser may run as a page or script if served inline from the app's origin: HTML, every XML type
# (browsers render `*+xml`, e.g. application/rdf+xml or application/xslt+xml, as a document that can hold
# XHTML <script>), scripts, CSS, PDF, Flash and saved web pages (message/rfc822). Matched as words in the type.
ACTIVE_TYPE_WORDS = ("html", "xml", "script", "css", "pdf", "flash", "rfc822")
ACTIVE_SUFFIXES = (".html", ".htm", ".shtml", ".xhtml", ".xht", ".svg", ".svgz", ".xml", ".xsl", ".xslt", ".js",
                   ".mjs", ".css", ".swf", ".pdf", ".mht", ".mhtml")


def is_active(content_type: str, path: str) -> bool:
    """Whether a file with this Content-Type (or, whatever its type, this name) must not be served inline."""
    kind = content_type.split(";")[0].strip().lower()
    return any(word in kind for word in ACTIVE_TYPE_WORDS) or path.lower().endswith(ACTIVE_SUFFIXES)


def client_key(scope, trust_forwarded: bool = False) -> str:
    """The client's address. With `trust_forwarded` (only behind the share tunnel, which connects from
    loopback) a loopback peer is keyed by its last X-Forwarded-For hop; otherwise the header is ignored,
    so a local user cannot pick a fresh key per guess."""
    host = (scope.get("client") or ("unknown", 0))[0]
    if trust_forwarded and host in ("127.0.0.1", "::1", "localhost"):
        for name, value in scope.get("headers") or ():
            if name == b"x-forwarded-for" and value.strip():
                return value.decode("latin-1").split(",")[-1].strip() or host
    return host


class ClientAddress:
    """ASGI middleware: remember the client of a login request for `LoginGuard` (a context variable)."""

    def __init__(self, app, trust_forwarded: bool = False):
        self.app = app
        self.trust_forwarded = trust_forwarded  # True only behind the share tunnel (`client_key`)

    async def __call__(self, scope, receive, send):
        if scope["type"] == "http" and scope["path"].rstrip("/").endswith("/login"):
            token = _client.set(client_key(scope, self.trust_forwarded))
            try:
                return await self.app(scope, receive, send)
            finally:
                _client.reset(token)
        return await self.app(scope, receive, send)


class FileHeaders:
    """ASGI middleware: no MIME sniffing on served files, and active content only as a download."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or "/file=" not in scope["path"] and "/file/" not in scope["path"]:
            return await self.app(scope, receive, send)
        path = scope["path"].lower()

        async def guarded_send(message):
            if message["type"] == "http.response.start":
                headers = [(k, v) for k, v in message.get("headers", [])
                           if k.lower() != b"x-content-type-options"]
                content_type = next((v.decode("latin-1").lower() for k, v in headers
                                     if k.lower() == b"content-type"), "")
                if is_active(content_type, path):
                    headers = [(k, v) for k, v in headers
                               if k.lower() not in (b"content-type", b"content-disposition")]
                    headers += [(b"content-type", b"application/octet-stream"),
                                (b"content-disposition", b"attachment")]
                headers.append((b"x-content-type-options", b"nosniff"))
                message = {**message, "headers": headers}
            await send(message)

        return await self.app(scope, receive, guarded_send)


@dataclass
class _Client:
    failures: int = 0
    next_try: float = 0.0      # monotonic time before which the next attempt waits
    last_seen: float = 0.0
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)


class LoginGuard:
    """Per-client back-off and logging for logins; give Gradio the bound coroutine `guard.check`.

    (Gradio awaits `auth` only when `inspect.iscoroutinefunction(auth)`; a bound async method
    passes that test, an object with an async `__call__` would not and would let everyone in.)
    """

    def __init__(self, users: dict[str, str]):
        self._users = dict(users)
        self._clients: dict[str, _Client] = {}

    def delay_after(self, failures: int) -> float:
        """Seconds a client waits before its next attempt after `failures` failures in a row."""
        return 0.0 if failures <= 0 else min(BACKOFF_BASE_S * 2 ** (failures - 1), BACKOFF_MAX_S)

    def _state(self, key: str) -> _Client:
        now = _now()
        if len(self._clients) > MAX_CLIENTS:
            stale = [k for k, c in self._clients.items() if now - c.last_seen > FORGET_AFTER_S]
            for k in stale or sorted(self._clients, key=lambda k: self._clients[k].last_seen)[:MAX_CLIENTS // 10]:
                del self._clients[k]
        state = self._clients.setdefault(key, _Client())
        if now - state.last_seen > FORGET_AFTER_S:
            state.failures = 0
        state.last_seen = now
        return state

    async def check(self, username: str, password: str) -> bool:
        """Wait out this client's back-off, then compare the password in constant time."""
        key = _client.get()
        state = self._state(key)
        async with state.lock:
            wait = state.next_try - _now()
            if wait > 0:
                await _sleep(wait)
            expected = self._users.get(username)
            ok = expected is not None and hmac.compare_digest(password.encode(), expected.encode())
            state.last_seen = _now()
            if ok:
                if state.failures:
                    log.warning("Login for user %r from %s succeeded after %d failed attempts.",
                                username, key, state.failures)
                state.failures, state.next_try = 0, 0.0
                return True
            state.failures += 1
            delay = self.delay_after(state.failures)
            state.next_try = _now() + delay
            log.warning("Failed login for user %r from %s (%d in a row); its next attempt waits %.1f s.",
                        username, key, state.failures, delay)
            return False
