"""The studio's HTTP API (FastAPI), used by its own page and by any other client.

Every ``/api`` call needs the access token printed at start, as ``Authorization: Bearer <token>``, or the studio's
cookie: the page trades the token for it once (``POST /api/login``, an HttpOnly SameSite=Strict cookie) and then
drops the token from its address, so the token never appears in a URL the page makes. Every call but
``POST /api/session`` and ``POST /api/login`` names its session in ``X-Studio-Session`` (or ``?session=``, for
event streams and download links). Errors are JSON ``{"detail": ..., "field": ...}`` with a 4xx status naming the
offending field.

Before any route runs, one middleware checks, in this order and before reading a byte of the body: the ``Host``
header (a DNS-rebinding page names its own host), the ``Origin`` of a browser's request, the token, and then
reads the body within a size and a time limit. Every answer carries headers that keep the page out of frames and
its address out of ``Referer`` (``Content-Security-Policy``, ``X-Frame-Options``, ``Referrer-Policy``).

    POST   /api/login                             -> sets the cookie (token in the Authorization header)
    POST   /api/session                           -> {"session": id}
    GET    /api/session                           -> what it holds: {"prompts", "rollouts", "limits"}
    DELETE /api/session                           -> forget it (its prompts and rollouts)
    GET    /api/checkpoints                       -> [{"id", "label", "method", "step"}]
    GET    /api/stored                            -> the unseen drawings: [{"task", "id", "episodes"}]
    POST   /api/prompts {"kind": "drawn", "samples": [[x, y, pen], ...], "board_angle": rad}
                        {"kind": "strokes", "strokes": [[[u, v], ...], ...], "board_angle": rad, "seed": int}
                        {"kind": "file", "name": "x.svg", "text": "<svg ...", "board_angle": rad, "seed": int}
                        {"kind": "stored", "task": int, "demo": int}   -> {"id", "source", "steps", "ink", ...}
    DELETE /api/prompts/{id}                      -> forget it
    GET    /api/prompts/{id}/task.json            -> the prompt as a task file for ``bpp eval --files``
    POST   /api/rollouts {"prompt_id", "checkpoint_id", "board_angle": rad or null (random), "seed", "max_steps",
                      "frames": 0 | 64 | 128 | 256}
    GET    /api/rollouts/{id}/events?since=N      -> server-sent events: start, step (action, cursor, pen, ink
                                                     segment, chamfer, attention on new inferences, and the
                                                     rendered frame as a base64 PNG if asked), end
    GET    /api/rollouts/{id}                     -> status and best Chamfer
    DELETE /api/rollouts/{id}                     -> stop it
    GET    /api/rollouts/{id}/episode.json | episode.gif | episode.mp4
"""

import asyncio
import base64
import hashlib
import hmac
import ipaddress
import json
import re
import threading
import time
from collections.abc import Collection
from importlib import resources
from typing import Annotated, Literal
from urllib.parse import urlsplit

from fastapi import Depends, FastAPI, Header, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse, StreamingResponse
from pydantic import BaseModel, ConfigDict, Field
from starlette.exceptions import HTTPException as StarletteHTTPException

from bpp.benchmarks.draw.studio.engine import Studio
from bpp.benchmarks.draw.studio.state import Rollout, StudioError
from bpp.network import client_key

ANGLE = Field(default=0.0, ge=-3.2, le=3.2, description="board angle, radians")


class _Body(BaseModel):
    model_config = ConfigDict(extra="forbid")


class DrawnPrompt(_Body):
    kind: Literal["drawn"]
    samples: list[Annotated[list[float], Field(min_length=3, max_length=3)]] = Field(min_length=2, max_length=5000)
    board_angle: float = ANGLE


class StrokesPrompt(_Body):
    kind: Literal["strokes"]
    strokes: list[list[Annotated[list[float], Field(min_length=2, max_length=2)]]] = Field(min_length=1, max_length=100)
    board_angle: float = ANGLE
    seed: int = Field(default=0, ge=0, le=2**31 - 1)
    label: str = Field(default="", max_length=200)


class FilePrompt(_Body):
    kind: Literal["file"]
    name: str = Field(min_length=1, max_length=200)
    text: str = Field(min_length=1)
    board_angle: float = ANGLE
    seed: int = Field(default=0, ge=0, le=2**31 - 1)


class StoredPrompt(_Body):
    kind: Literal["stored"]
    task: int = Field(ge=0, le=2**31 - 1)
    demo: int = Field(default=0, ge=0, le=2**31 - 1)


class RolloutRequest(_Body):
    prompt_id: str = Field(min_length=1, max_length=64)
    checkpoint_id: str = Field(min_length=1, max_length=64)
    board_angle: float | None = Field(default=None, ge=-3.2, le=3.2)
    seed: int = Field(default=0, ge=0, le=2**31 - 1)
    max_steps: int = Field(default=400, ge=1, le=2**31 - 1)
    frames: Literal[0, 64, 128, 256] = 0
    """Send each step's rendered frame (this side, px) as a base64 PNG in its event (0: none)."""


PromptRequest = Annotated[DrawnPrompt | StrokesPrompt | FilePrompt | StoredPrompt, Field(discriminator="kind")]

PAGE = "page.html"
SECURITY_HEADERS = [
    (b"x-content-type-options", b"nosniff"),
    (b"x-frame-options", b"DENY"),
    (b"referrer-policy", b"no-referrer"),
    (b"cross-origin-opener-policy", b"same-origin"),
    (b"cross-origin-resource-policy", b"same-origin"),
    (b"cache-control", b"no-store"),
]


def _csp(page: str) -> str:
    """A Content-Security-Policy allowing exactly the page's own inline script and style (by their hashes)."""

    def hashes(tag: str) -> str:
        blocks = re.findall(rf"<{tag}>(.*?)</{tag}>", page, flags=re.S)
        return " ".join(f"'sha256-{base64.b64encode(hashlib.sha256(b.encode()).digest()).decode()}'" for b in blocks)

    return (
        f"default-src 'none'; script-src {hashes('script')}; style-src {hashes('style')}; img-src 'self' data:; "
        "connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'none'"
    )


def host_allowed(host: str, names: Collection[str]) -> bool:
    """Whether a ``Host`` header names this server: an IP address (a page served by another site cannot make the
    browser send one of those for its own requests: DNS rebinding needs a name), ``localhost``, or one of `names`."""
    if host.startswith("["):
        host = host[1 : host.find("]")] if "]" in host else host
    elif host.count(":") == 1:
        host = host.rsplit(":", 1)[0]
    host = host.lower().rstrip(".")
    try:
        ipaddress.ip_address(host)
        return True
    except ValueError:
        return host == "localhost" or host in {n.lower().rstrip(".") for n in names}


def _reply(status: int, detail: str, field: str):
    body = json.dumps({"detail": detail, "field": field}).encode()
    return [
        {
            "type": "http.response.start",
            "status": status,
            "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())],
        },
        {"type": "http.response.body", "body": body},
    ]


class _Guard:
    """ASGI middleware in front of every route. It answers before the app sees the request (and before the body
    is read) when the Host is not this server's (400), a browser's Origin is another site's (403), or an ``/api``
    call lacks the token (401); then it reads the body, refusing one over `limit` bytes (413) or slower than
    `timeout_s` (408), and it adds the security headers to every answer."""

    def __init__(self, app, authorised, hosts: Collection[str], limit: int, timeout_s: float, csp: str):
        self.app, self.authorised, self.hosts = app, authorised, hosts
        self.limit, self.timeout_s = limit, timeout_s
        self.headers = [*SECURITY_HEADERS, (b"content-security-policy", csp.encode())]

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)

        async def secured(message):
            if message["type"] == "http.response.start":
                names = {k.lower() for k, _ in message.get("headers", [])}
                extra = [(k, v) for k, v in self.headers if k not in names]
                message = {**message, "headers": [*message.get("headers", []), *extra]}
            await send(message)

        refusal = self._refusal(scope)
        if refusal is not None:
            for message in _reply(*refusal):
                await secured(message)
            return None
        headers = dict(scope.get("headers") or [])
        declared = headers.get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.limit:
            for message in _reply(413, f"request body over {self.limit} bytes", "body"):
                await secured(message)
            return None
        body, more = b"", True
        deadline = time.monotonic() + self.timeout_s
        while more:
            try:
                message = await asyncio.wait_for(receive(), max(0.0, deadline - time.monotonic()))
            except TimeoutError:
                for message in _reply(408, f"the request body did not arrive within {self.timeout_s:g} s", "body"):
                    await secured(message)
                return None
            if message["type"] != "http.request":
                return None  # the client went away
            body += message.get("body", b"")
            more = message.get("more_body", False)
            if len(body) > self.limit:
                for message in _reply(413, f"request body over {self.limit} bytes", "body"):
                    await secured(message)
                return None
        sent = False

        async def replay():
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        return await self.app(scope, replay, secured)

    def _refusal(self, scope) -> tuple[int, str, str] | None:
        headers = {}
        for key, value in scope.get("headers") or []:
            headers.setdefault(key.decode("latin-1").lower(), value.decode("latin-1"))
        host = headers.get("host")
        if host is not None and not host_allowed(host, self.hosts):
            return 400, f"this studio does not answer to the host name {host[:100]!r}", "host"
        if not scope["path"].startswith("/api"):
            return None
        origin = headers.get("origin")
        if origin is not None and (origin == "null" or urlsplit(origin).netloc.lower() != (host or "").lower()):
            return 403, f"requests from another site ({origin[:100]}) are refused", "origin"
        if scope["path"] == "/api/login":
            headers.pop("cookie", None)  # only the token itself buys a cookie
        if not self.authorised(headers):
            return 401, "missing or wrong access token (see the URL `bpp studio` printed)", "token"
        return None


class _Stream(StreamingResponse):
    """A streaming answer that calls `on_close` however it ends (sent, client gone, server stopping)."""

    def __init__(self, content, on_close, **kw):
        super().__init__(content, **kw)
        self.on_close = on_close

    async def __call__(self, scope, receive, send):
        try:
            await super().__call__(scope, receive, send)
        finally:
            self.on_close()


def create_app(studio: Studio, token: str, hosts: Collection[str] = ()) -> FastAPI:
    """The studio's FastAPI app; `token` guards every API call; `hosts` are the host names it answers to besides
    IP addresses and ``localhost`` (e.g. the machine's name, for a phone on the same network)."""
    app = FastAPI(title="bpp studio", docs_url=None, redoc_url=None, openapi_url=None)
    page_html = resources.files("bpp.benchmarks.draw.studio").joinpath(PAGE).read_text(encoding="utf-8")
    cookie = _Cookie(token)
    _answer_errors(app)
    session = _session_dependency(studio)
    _page_routes(app, page_html, token, cookie)
    _session_routes(app, studio, session)
    _prompt_routes(app, studio, session)
    _rollout_routes(app, studio, session)
    app.add_middleware(
        _Guard,
        authorised=cookie.authorised,
        hosts=tuple(hosts),
        limit=studio.limits.max_body_bytes,
        timeout_s=studio.limits.body_timeout_s,
        csp=_csp(page_html),
    )
    return app


class _Cookie:
    """What a browser holds once it has shown the token: an HttpOnly cookie, named per token (two studios on one
    machine keep their own), whose value is derived from the token."""

    def __init__(self, token: str):
        self.token = token
        self.name = f"bpp_studio_{hashlib.sha256(token.encode()).hexdigest()[:12]}"
        self.value = hmac.new(token.encode(), b"studio cookie", hashlib.sha256).hexdigest()

    def authorised(self, headers: dict[str, str]) -> bool:
        """Whether a request carries the token (a bearer header) or the cookie."""
        given = headers.get("authorization", "")
        if given.startswith("Bearer ") and hmac.compare_digest(given[7:].encode(), self.token.encode()):
            return True
        cookies = [c.strip().partition("=") for c in headers.get("cookie", "").split(";")]
        return any(name == self.name and hmac.compare_digest(v.encode(), self.value.encode()) for name, _, v in cookies)

    def set(self, response) -> None:
        response.set_cookie(self.name, self.value, httponly=True, samesite="strict", path="/")


def _answer_errors(app: FastAPI) -> None:
    """Every refusal as ``{"detail", "field"}`` JSON with its status, the field named the way the page names it."""

    @app.exception_handler(StudioError)
    async def _studio_error(_: Request, err: StudioError):
        return JSONResponse({"detail": str(err), "field": err.field}, status_code=err.status)

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(_: Request, err: StarletteHTTPException):
        field = "body" if err.status_code == 400 else ""  # FastAPI's 400: a body it could not parse
        return JSONResponse({"detail": str(err.detail), "field": field}, status_code=err.status_code)

    @app.exception_handler(RequestValidationError)
    async def _invalid(_: Request, err: RequestValidationError):
        first = err.errors()[0]
        where = [str(part) for part in first.get("loc", ())]
        if where == ["body"]:  # the body as a whole: absent, or not JSON
            where = ["body"]
        elif where[:1] and where[0] in ("body", "query", "header", "path"):  # where the input was
            where = where[1:]
        if where[:1] and where[0] in ("drawn", "strokes", "file", "stored"):  # which kind of prompt
            where = where[1:]
        if first.get("type", "").startswith("union_tag"):
            where = ["kind"]
        if first.get("type") == "json_invalid":
            where = ["body"]
        field = where[0] if where else ""
        return JSONResponse(
            {"detail": f"{'.'.join(where) or 'request'}: {first.get('msg')}", "field": field}, status_code=422
        )


def _session_dependency(studio: Studio):
    """The session a request names (its X-Studio-Session header, or ``?session=`` where EventSource cannot set
    headers), checked to exist: a parameter type for the routes."""

    def session_id(
        x_studio_session: Annotated[str | None, Header()] = None,
        session_query: Annotated[str | None, Query(alias="session", max_length=64)] = None,
    ) -> str:
        sid = x_studio_session or session_query
        if not sid:
            raise StudioError("name your session in the X-Studio-Session header (POST /api/session)", "session", 400)
        studio.session(sid)
        return sid

    return Annotated[str, Depends(session_id)]


def _page_routes(app: FastAPI, page_html: str, token: str, cookie: _Cookie) -> None:
    """The page, and the token traded for the cookie (from the page's address, or by the page's script)."""

    @app.get("/", response_class=HTMLResponse)
    def page(request: Request):
        given = request.query_params.get("token")
        if given is not None:  # an address with the token: trade it for the cookie and drop it from the address
            answer = RedirectResponse("/", status_code=303)
            if hmac.compare_digest(given.encode(), token.encode()):
                cookie.set(answer)
            return answer
        return HTMLResponse(page_html)

    @app.post("/api/login")
    def login() -> JSONResponse:
        answer = JSONResponse({"cookie": True})
        cookie.set(answer)
        return answer


def _session_routes(app: FastAPI, studio: Studio, SessionId) -> None:  # noqa: N803 - a type, as FastAPI reads it
    """Sessions, and what every session may read: the checkpoints and the stored demonstrations."""

    @app.post("/api/session")
    def new_session(request: Request) -> dict:
        client = client_key(request.client.host if request.client else "")
        return {"session": studio.new_session(client), "limits": studio.limits.__dict__}

    @app.get("/api/session")
    def session_info(sid: SessionId) -> dict:
        return studio.session_info(sid)

    @app.delete("/api/session")
    def end_session(sid: SessionId) -> dict:
        studio.end_session(sid)
        return {"session": sid, "ended": True}

    @app.get("/api/checkpoints")
    def checkpoints() -> list[dict]:
        return [c.public() for c in studio.checkpoints.values()]

    @app.get("/api/stored")
    def stored() -> list[dict]:
        return studio.stored_prompts()


def _prompt_routes(app: FastAPI, studio: Studio, SessionId) -> None:  # noqa: N803 - a type, as FastAPI reads it
    """A session's prompts: drawn, strokes, a drawing file or a stored demonstration; deleted; as a task file."""

    @app.post("/api/prompts")
    def add_prompt(body: PromptRequest, sid: SessionId) -> dict:
        if isinstance(body, DrawnPrompt):
            prompt = studio.add_drawn_prompt(sid, body.samples, body.board_angle)
        elif isinstance(body, StrokesPrompt):
            prompt = studio.add_strokes_prompt(sid, body.strokes, body.board_angle, body.seed, body.label)
        elif isinstance(body, FilePrompt):
            prompt = studio.add_file_prompt(sid, body.name, body.text, body.board_angle, body.seed)
        else:
            prompt = studio.add_stored_prompt(sid, body.task, body.demo)
        return prompt.public(ink=True)

    @app.delete("/api/prompts/{pid}")
    def delete_prompt(pid: str, sid: SessionId) -> dict:
        studio.delete_prompt(sid, pid)
        return {"id": pid, "deleted": True}

    @app.get("/api/prompts/{pid}/task.json")
    def task_file(pid: str, sid: SessionId) -> JSONResponse:
        task = studio.prompt_task_file(sid, pid)
        headers = {"Content-Disposition": f'attachment; filename="studio-{studio.prompt(sid, pid).id}.json"'}
        return JSONResponse(task, headers=headers)


def _rollout_routes(app: FastAPI, studio: Studio, SessionId) -> None:  # noqa: N803 - a type, as FastAPI reads it
    """A session's rollouts: started, read as they run (server-sent events), stopped, downloaded."""

    @app.post("/api/rollouts")
    def start(body: RolloutRequest, sid: SessionId) -> dict:
        rollout = studio.start_rollout(
            sid, body.prompt_id, body.checkpoint_id, body.board_angle, body.seed, body.max_steps, body.frames
        )
        return rollout.public()

    @app.get("/api/rollouts/{rid}")
    def status(rid: str, sid: SessionId) -> dict:
        return studio.rollout(sid, rid).public()

    @app.delete("/api/rollouts/{rid}")
    def stop(rid: str, sid: SessionId) -> dict:
        return studio.stop_rollout(sid, rid).public()

    @app.get("/api/rollouts/{rid}/events")
    async def events(
        rid: str,
        sid: SessionId,
        request: Request,
        since: int = Query(default=0, ge=0, le=2**31 - 1),
        last_event_id: Annotated[str | None, Header()] = None,
    ):
        rollout = studio.rollout(sid, rid)  # 404 before the stream starts
        if last_event_id is not None:  # a browser reconnecting resumes after what it has (an id it was sent)
            if not re.fullmatch(r"[0-9]{1,9}", last_event_id):
                raise StudioError("Last-Event-ID must be an event id this studio sent (a number)", "last-event-id", 422)
            since = max(since, int(last_event_id) + 1)
        studio.open_stream(sid, rollout)
        return _Stream(
            _event_stream(rollout, since, request),
            on_close=lambda: _closed(sid, rollout),
            media_type="text/event-stream",
        )

    def _closed(sid: str, rollout: Rollout) -> None:
        studio.close_stream(sid, rollout)
        if rollout.running and not rollout.readers:  # its reader left before the end: stop drawing for nobody
            rollout.stop.set()

    @app.get("/api/rollouts/{rid}/episode.json")
    def episode(rid: str, sid: SessionId) -> JSONResponse:
        data = studio.episode(sid, rid)
        headers = {"Content-Disposition": f'attachment; filename="rollout-{data["id"]}.json"'}
        return JSONResponse(data, headers=headers)

    @app.get("/api/rollouts/{rid}/episode.{fmt}")
    async def animation(rid: str, fmt: Literal["gif", "mp4"], sid: SessionId, request: Request):
        cancel = threading.Event()
        render = asyncio.ensure_future(asyncio.to_thread(studio.animation, sid, rid, fmt, cancel))
        try:
            while not render.done():  # a client that leaves stops the render (it is seconds of CPU)
                await asyncio.wait({render}, timeout=0.2)
                if not render.done() and await request.is_disconnected():
                    cancel.set()
        finally:
            cancel.set()  # also when the server stops meanwhile
        path = await render
        handle = path.open("rb")  # opened now: a later eviction of the file cannot break this answer

        def chunks():
            with handle:
                while chunk := handle.read(1 << 16):
                    yield chunk

        media = "image/gif" if fmt == "gif" else "video/mp4"
        headers = {"Content-Disposition": f'attachment; filename="rollout-{studio.rollout(sid, rid).id}.{fmt}"'}
        return StreamingResponse(chunks(), media_type=media, headers=headers)


async def _event_stream(rollout: Rollout, since: int, request: Request):
    """The rollout's events from `since` on, as server-sent events, until its end (at once if it has ended)."""
    sent = since
    while True:
        rollout.last_read = time.monotonic()
        finished = not rollout.running  # read before the events: the end event is in before the status changes
        while sent < len(rollout.events):
            yield f"id: {sent}\ndata: {rollout.event_text(sent)}\n\n"
            sent += 1
        if finished or await request.is_disconnected():
            return
        await asyncio.sleep(0.02)
