"""Who is calling: API tokens (header ``X-API-Token`` or ``Authorization: Bearer``) and, for the study page,
a session id (not the token) held in an HttpOnly, SameSite=Strict cookie set by ``POST /v1/session`` and
revoked by ``DELETE /v1/session``."""

from __future__ import annotations

import hmac

from fastapi import HTTPException, Request

COOKIE = "ardflow_token"


class TokenAuth:
    """FastAPI dependency: the caller's name (the token's owner; "anonymous" without authentication).

    Parameters
    ----------
    tokens : dict of owner name to token
        Empty: the service runs without authentication (loopback only, see ``ardflow serve``).
    """

    def __init__(self, tokens: dict[str, str]):
        self.tokens = dict(tokens)
        # the page's sign-ins: a random session id (the cookie) -> its owner; the token itself never leaves
        # the sign-in request, and signing out revokes the id (a restart signs everyone out)
        self.sessions: dict[str, str] = {}

    def open_session(self, owner: str) -> str:
        """A new session id for ``owner`` (what the page's cookie holds)."""
        import secrets

        sid = secrets.token_urlsafe(32)
        self.sessions[sid] = owner
        return sid

    def close_session(self, sid: str | None) -> None:
        """Revoke a session id: its cookie authenticates nothing from now on."""
        self.sessions.pop(sid or "", None)

    @property
    def required(self) -> bool:
        return bool(self.tokens)

    def owner(self, given: str | None) -> str | None:
        """The owner of token ``given``, or None. Every comparison runs, each in constant time."""
        owner = None
        for name, tok in self.tokens.items():
            if given is not None and hmac.compare_digest(given.encode(), tok.encode()):
                owner = name
        return owner

    async def __call__(self, request: Request) -> str:
        if not self.tokens:
            return "anonymous"
        given = request.headers.get("x-api-token")
        if given is None:
            h = request.headers.get("authorization", "")
            given = h[7:] if h.lower().startswith("bearer ") else None
        owner = self.owner(given) if given is not None else self.sessions.get(request.cookies.get(COOKIE) or "")
        if owner is None:
            raise HTTPException(401, "missing or wrong API token", headers={"WWW-Authenticate": "Bearer"})
        return owner


class StudyAccess:
    """FastAPI dependency of every route under ``/studies/{sid}``: passes when the caller owns the study or
    is an admin; otherwise 404, exactly as for a study that does not exist (another user's ids
    are not confirmed)."""

    def __init__(self, auth: TokenAuth, registry, admins: list[str]):
        self.auth, self.registry, self.admins = auth, registry, set(admins)

    def sees(self, owner: str, meta: dict) -> bool:
        """Whether ``owner`` may see the study of ``meta`` (a damaged entry, whose owner is unknown: admins
        only). Without authentication, or with one token (one user), everything is seen."""
        return (len(self.auth.tokens) <= 1 or owner in self.admins
                or (meta.get("owner") is not None and meta.get("owner") == owner))

    async def __call__(self, sid: str, request: Request) -> None:
        owner = await self.auth(request)
        # the owner alone decides (cached: an entry's owner never changes); the route reads the status
        if not (self.registry.study_dir(sid) / "meta.json").exists() or not self.sees(
                owner, {"owner": self.registry.owner(sid)}):
            raise HTTPException(404, f"no study {sid!r}")
