"""Who is calling: API tokens (header ``X-API-Token`` or ``Authorization: Bearer``) and, for the study page,
the same token held in an HttpOnly, SameSite=Strict cookie set by ``POST /v1/session``."""

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
            given = h[7:] if h.lower().startswith("bearer ") else request.cookies.get(COOKIE)
        owner = self.owner(given)
        if owner is None:
            raise HTTPException(401, "missing or wrong API token", headers={"WWW-Authenticate": "Bearer"})
        return owner
