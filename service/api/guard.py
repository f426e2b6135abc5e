"""Request guards applied before routing, authentication and parsing (pure ASGI middleware).

* **Body size**: bytes are counted as they arrive, chunked or not; a request over the limit is answered
  413 before its body is read whole (a ``Content-Length`` over the limit before any of it is read).
* **Host**: with ``allowed_hosts`` the ``Host`` header must name one of them (a DNS-rebinding page cannot
  talk to a service on loopback under its own name), else 400.
* **Content type**: every ``POST`` (an empty one too) must be declared as JSON, or as CSV on the data-set
  route (a cross-site form cannot send those without a pre-flight), else 415.
* **Duplicate keys**: a JSON body whose object repeats a key is refused (422), not read with the last one.
* **Cross-site requests**: a state change (``POST``, ``PUT``, ``PATCH``, ``DELETE``) authenticated by the
  page's cookie alone must come from the page's own origin: ``Sec-Fetch-Site`` same-origin (or none, typed
  by the user) and an ``Origin`` naming this host and port; without either header it is refused (403).
  SameSite does not separate two ports of one host, so the cookie alone proves nothing. Requests with a
  token header cannot be forged cross-site (a custom header needs a pre-flight) and are not checked.
"""

from __future__ import annotations

import json
import re


async def _answer(send, status: int, detail: str) -> None:
    body = json.dumps({"detail": detail}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]})
    await send({"type": "http.response.body", "body": body})


_HOST = re.compile(r"(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9](?:[A-Za-z0-9.-]{0,251}[A-Za-z0-9])?)(?::[0-9]{1,5})?")


def host_name(host: str) -> str | None:
    """The name of a ``Host`` header (lower case, an IPv6 literal in brackets), or None unless the whole header
    is a name or address with an optional port (``127.0.0.1:1@evil.example`` is not)."""
    m = _HOST.fullmatch(host.strip())
    return m.group(1).lower() if m else None


STATE_CHANGES = ("POST", "PUT", "PATCH", "DELETE")


def _cookie_only(headers: dict) -> bool:
    """Authenticated (if at all) by the sign-in cookie alone: no token header a cross-site page could not set."""
    from ardflow.service.api.auth import COOKIE

    if "x-api-token" in headers or headers.get("authorization", "").lower().startswith("bearer "):
        return False
    return any(part.strip().startswith(COOKIE + "=") for part in headers.get("cookie", "").split(";"))


def same_origin(headers: dict) -> bool:
    """Whether a browser says the request comes from this host and port (``Origin``, ``Sec-Fetch-Site``)."""
    site = headers.get("sec-fetch-site")
    if site is not None and site not in ("same-origin", "none"):
        return False
    origin = headers.get("origin")
    if origin is None:
        return site is not None  # a browser that sends neither header is not one we can vouch for
    if origin == "null" or "://" not in origin:
        return False
    return origin.split("://", 1)[1].rstrip("/").lower() == headers.get("host", "").lower()


class _Duplicate(Exception):
    pass


def _no_duplicates(pairs):
    seen = {}
    for k, v in pairs:
        if k in seen:
            raise _Duplicate(k)
        seen[k] = v
    return seen


def _duplicate_key(body: bytes) -> str | None:
    """The first key that an object of the JSON ``body`` repeats (None: none, or not JSON at all, which the
    route's own parser answers)."""
    try:
        json.loads(body, object_pairs_hook=_no_duplicates)
    except _Duplicate as exc:
        return str(exc.args[0])
    except (ValueError, RecursionError):
        return None
    return None


def _hardened(send):
    """``send`` with every answer marked: never sniffed into another type, never framed by another origin (an
    HTML page that sets its own policy keeps it; the others get ``frame-ancestors 'none'``)."""
    async def out(msg):
        if msg["type"] == "http.response.start":
            have = {k.lower() for k, _ in msg.get("headers", [])}
            extra = [(b"x-content-type-options", b"nosniff"), (b"x-frame-options", b"DENY")]
            if b"content-security-policy" not in have:
                extra.append((b"content-security-policy", b"frame-ancestors 'none'"))
            msg = {**msg, "headers": [*msg.get("headers", []), *(h for h in extra if h[0] not in have)]}
        await send(msg)

    return out


class RequestGuard:
    """ASGI middleware: body-size limit, Host allow-list, Content-Type of POST bodies."""

    def __init__(self, app, *, max_body: int, allowed_hosts: list[str] | None = None,
                 csv_paths: tuple[str, ...] = ()):
        self.app, self.max_body = app, max_body
        self.allowed_hosts = {h.lower() for h in allowed_hosts} if allowed_hosts else None
        self.csv_paths = csv_paths

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        send = _hardened(send)
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        if self.allowed_hosts is not None:
            host = headers.get("host", "")
            name = host_name(host)
            if name is None or name not in self.allowed_hosts:
                return await _answer(send, 400, f"Host {host[:100]!r} is not served here")
        cl = headers.get("content-length")
        if cl is not None:
            if not cl.isdigit():
                return await _answer(send, 400, "invalid Content-Length")
            if int(cl) > self.max_body:
                return await _answer(send, 413, f"request body larger than {self.max_body / 2**20:g} MB")
        method = scope.get("method", "GET")
        if method in STATE_CHANGES and _cookie_only(headers) and not same_origin(headers):
            return await _answer(send, 403, "cross-site request refused: a change made with the page's sign-in "
                                            "cookie must come from the page itself (Origin / Sec-Fetch-Site)")
        if method == "POST" or (method in ("PUT", "PATCH") and (cl not in (None, "0")
                                                                 or "transfer-encoding" in headers)):
            ctype = headers.get("content-type", "").split(";")[0].strip().lower()
            wanted = ("text/csv", "application/octet-stream") if scope["path"] in self.csv_paths \
                else ("application/json",)
            if ctype not in wanted:
                return await _answer(send, 415, f"Content-Type must be {' or '.join(wanted)}, not {ctype or 'missing'!r}")
        if method not in ("POST", "PUT", "PATCH"):
            return await self.app(scope, receive, send)
        # read the body here, counting bytes, so that no route, dependency or parser ever holds more
        # than the limit (a chunked body has no Content-Length to refuse it by)
        chunks, seen = [], 0
        while True:
            msg = await receive()
            if msg["type"] == "http.disconnect":
                return
            body = msg.get("body", b"")
            seen += len(body)
            if seen > self.max_body:
                return await _answer(send, 413, f"request body larger than {self.max_body / 2**20:g} MB")
            chunks.append(body)
            if not msg.get("more_body", False):
                break
        body = b"".join(chunks)
        if body.strip() and headers.get("content-type", "").split(";")[0].strip().lower() == "application/json":
            dup = _duplicate_key(body)
            if dup is not None:
                return await _answer(send, 422, f"duplicate key {dup[:60]!r} in the JSON body (which one was "
                                                "meant is ambiguous)")
        replay = [{"type": "http.request", "body": body, "more_body": False}]

        async def replayed():
            if replay:
                return replay.pop()
            return await receive()

        await self.app(scope, replayed, send)
