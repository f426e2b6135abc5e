"""The study page: ``GET /`` lists the studies with their live progress and links, and submits new ones.

One HTML file (``page.html``: no CDN, no build step). It talks to the same ``/v1`` API as every other
client; a browser cannot put the token in a header of a link or an ``EventSource``, so
``POST /v1/session`` puts it in an HttpOnly, SameSite=Strict cookie that :class:`TokenAuth` also reads.
Cross-site requests carry no such cookie, and every POST must be JSON (:mod:`.guard`), so a foreign page
cannot act with it.
"""

from __future__ import annotations

import secrets
from pathlib import Path

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import HTMLResponse, Response
from pydantic import BaseModel, Field

from ardflow.service.api.auth import COOKIE, TokenAuth
from ardflow.service.api.schemas import API_VERSION

PAGE = Path(__file__).with_name("page.html")


class SessionRequest(BaseModel):
    token: str = Field(min_length=1, max_length=512)


def page_router(auth: TokenAuth) -> APIRouter:
    """``GET /`` (the page) and ``POST``/``DELETE /v1/session`` (sign in and out of the page)."""
    r = APIRouter()
    html = PAGE.read_text()

    @r.get("/", response_class=HTMLResponse, include_in_schema=False)
    def page() -> HTMLResponse:
        nonce = secrets.token_urlsafe(16)
        csp = (f"default-src 'self'; script-src 'nonce-{nonce}'; style-src 'unsafe-inline'; img-src 'self' data:; "
               "frame-ancestors 'none'; form-action 'none'; base-uri 'none'")
        return HTMLResponse(html.replace("__NONCE__", nonce),
                            headers={"Content-Security-Policy": csp, "X-Content-Type-Options": "nosniff",
                                     "Referrer-Policy": "no-referrer", "Cache-Control": "no-store"})

    @r.post(f"/{API_VERSION}/session", status_code=204)
    def sign_in(req: SessionRequest, request: Request) -> Response:
        if auth.required and auth.owner(req.token) is None:
            raise HTTPException(401, "wrong API token")
        resp = Response(status_code=204)
        if auth.required:
            resp.set_cookie(COOKIE, req.token, httponly=True, samesite="strict", path="/",
                            secure=request.url.scheme == "https")
        return resp

    @r.delete(f"/{API_VERSION}/session", status_code=204)
    def sign_out() -> Response:
        resp = Response(status_code=204)
        resp.delete_cookie(COOKIE, path="/")
        return resp

    return r
