"""The study page: ``GET /`` lists the studies with their live progress and links, and submits new ones.

One HTML file (``page.html``: no CDN, no build step). It talks to the same ``/v1`` API as every other
client; a browser cannot put the token in a header of a link or an ``EventSource``, so
``POST /v1/session`` exchanges it for a session id in an HttpOnly, SameSite=Strict cookie that
:class:`TokenAuth` also reads (``DELETE /v1/session`` revokes it).
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
from ardflow.service.api.guard import same_origin
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
        headers = {k.lower(): v for k, v in request.headers.items()}
        if ("origin" in headers or "sec-fetch-site" in headers) and not same_origin(headers):
            # a foreign page must not sign a browser in (login CSRF): only the page itself, or a client
            # that is not a browser (no Origin at all)
            raise HTTPException(403, "cross-site sign-in refused: sign in from the study page itself")
        owner = auth.owner(req.token) if auth.required else "anonymous"
        if owner is None:
            raise HTTPException(401, "wrong API token")
        resp = Response(status_code=204)
        if auth.required:
            resp.set_cookie(COOKIE, auth.open_session(owner), httponly=True, samesite="strict", path="/",
                            secure=request.url.scheme == "https")
        return resp

    @r.delete(f"/{API_VERSION}/session", status_code=204)
    def sign_out(request: Request) -> Response:
        auth.close_session(request.cookies.get(COOKIE))
        resp = Response(status_code=204)
        resp.delete_cookie(COOKIE, path="/")
        return resp

    return r


def docs_router() -> APIRouter:
    """``GET /docs``: Swagger UI over ``/openapi.json``, its script and style served from the installed
    ``swagger-ui-bundle`` package (``/docs/assets/...``): the page of the API's docs loads nothing from another
    origin, which could otherwise run script beside the sign-in cookie."""
    import swagger_ui_bundle
    from fastapi.openapi.docs import get_swagger_ui_html

    assets = Path(swagger_ui_bundle.swagger_ui_path)
    files = {"swagger-ui-bundle.js": "text/javascript", "swagger-ui.css": "text/css",
             "favicon-32x32.png": "image/png"}
    r = APIRouter()

    @r.get("/docs", response_class=HTMLResponse, include_in_schema=False)
    def docs() -> HTMLResponse:
        return get_swagger_ui_html(openapi_url="/openapi.json", title="ardflow API",
                                   swagger_js_url="/docs/assets/swagger-ui-bundle.js",
                                   swagger_css_url="/docs/assets/swagger-ui.css",
                                   swagger_favicon_url="/docs/assets/favicon-32x32.png")

    @r.get("/docs/assets/{name}", include_in_schema=False)
    def asset(name: str) -> Response:
        if name not in files:
            raise HTTPException(404, f"no {name!r}")
        return Response((assets / name).read_bytes(), media_type=files[name],
                        headers={"Cache-Control": "public, max-age=86400"})

    return r
