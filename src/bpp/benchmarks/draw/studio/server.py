"""The studio's HTTP API (FastAPI), used by its own page and by any other client.

Every ``/api`` call needs the access token printed at start, as ``Authorization: Bearer <token>`` (or, where a
client cannot set headers, e.g. the browser's EventSource, ``?token=<token>``), and every call but
``POST /api/session`` names its session in ``X-Studio-Session`` (or ``?session=``). Errors are JSON
``{"detail": ..., "field": ...}`` with a 4xx status naming the offending field.

    POST   /api/session                           -> {"session": id}
    DELETE /api/session                           -> forget it (its prompts and rollouts)
    GET    /api/checkpoints                       -> [{"id", "label", "method", "step"}]
    GET    /api/stored                            -> the unseen drawings: [{"task", "id", "episodes"}]
    POST   /api/prompts {"kind": "drawn", "samples": [[x, y, pen], ...], "board_angle": rad}
                        {"kind": "strokes", "strokes": [[[u, v], ...], ...], "board_angle": rad, "seed": int}
                        {"kind": "file", "name": "x.svg", "text": "<svg ...", "board_angle": rad, "seed": int}
                        {"kind": "stored", "task": int, "demo": int}   -> {"id", "source", "steps", ...}
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
import hmac
import json
import secrets
import tempfile
import threading
import time
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal

from fastapi import Depends, FastAPI, Header, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, StreamingResponse
from pydantic import BaseModel, ConfigDict, Field
from starlette.background import BackgroundTask

from bpp.benchmarks.draw.studio.engine import Studio, StudioError

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


class FilePrompt(_Body):
    kind: Literal["file"]
    name: str = Field(min_length=1, max_length=200)
    text: str = Field(min_length=1)
    board_angle: float = ANGLE
    seed: int = Field(default=0, ge=0, le=2**31 - 1)


class StoredPrompt(_Body):
    kind: Literal["stored"]
    task: int = Field(ge=0)
    demo: int = Field(default=0, ge=0)


class RolloutRequest(_Body):
    prompt_id: str = Field(min_length=1, max_length=64)
    checkpoint_id: str = Field(min_length=1, max_length=64)
    board_angle: float | None = Field(default=None, ge=-3.2, le=3.2)
    seed: int = Field(default=0, ge=0, le=2**31 - 1)
    max_steps: int = Field(default=400, ge=1)
    frames: Literal[0, 64, 128, 256] = 0
    """Send each step's rendered frame (this side, px) as a base64 PNG in its event (0: none)."""


PromptRequest = Annotated[DrawnPrompt | StrokesPrompt | FilePrompt | StoredPrompt, Field(discriminator="kind")]


class _LimitBody:
    """ASGI middleware: a request body over `limit` bytes gets 413 before the app reads it."""

    def __init__(self, app, limit: int):
        self.app, self.limit = app, limit

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        declared = dict(scope.get("headers") or []).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.limit:
            return await _too_large(send, self.limit)
        # Read the body here (declared or chunked), refusing it as soon as it passes the limit, then hand it on.
        body, more = b"", True
        while more:
            message = await receive()
            if message["type"] != "http.request":
                return  # the client went away
            body += message.get("body", b"")
            more = message.get("more_body", False)
            if len(body) > self.limit:
                return await _too_large(send, self.limit)
        sent = False

        async def replay():
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        return await self.app(scope, replay, send)


async def _too_large(send, limit: int) -> None:
    body = json.dumps({"detail": f"request body over {limit} bytes", "field": "body"}).encode()
    await send({"type": "http.response.start", "status": 413, "headers": [(b"content-type", b"application/json")]})
    await send({"type": "http.response.body", "body": body})


def create_app(studio: Studio, token: str) -> FastAPI:
    """The studio's FastAPI app; `token` guards every API call."""
    app = FastAPI(title="bpp studio", docs_url=None, redoc_url=None, openapi_url=None)
    media = Path(tempfile.mkdtemp(prefix="media-", dir=studio.workdir))
    renders = threading.BoundedSemaphore(2)

    @app.exception_handler(StudioError)
    async def _studio_error(_: Request, err: StudioError):
        return JSONResponse({"detail": str(err), "field": err.field}, status_code=err.status)

    @app.exception_handler(RequestValidationError)
    async def _invalid(_: Request, err: RequestValidationError):
        first = err.errors()[0]
        where = [str(part) for part in first.get("loc", ())]
        if where[:1] and where[0] in ("body", "query", "header", "path"):  # where the input was
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

    def authorised(
        authorization: Annotated[str | None, Header()] = None,
        token_query: Annotated[str | None, Query(alias="token")] = None,
    ) -> None:
        given = authorization[7:] if authorization and authorization.startswith("Bearer ") else token_query
        if not given or not hmac.compare_digest(given.encode(), token.encode()):
            raise StudioError("missing or wrong access token (see the URL `bpp studio` printed)", "token", 401)

    def session_id(
        x_studio_session: Annotated[str | None, Header()] = None,
        session_query: Annotated[str | None, Query(alias="session")] = None,
    ) -> str:
        sid = x_studio_session or session_query
        if not sid:
            raise StudioError("name your session in the X-Studio-Session header (POST /api/session)", "session", 400)
        studio.session(sid)
        return sid

    auth = [Depends(authorised)]
    SessionId = Annotated[str, Depends(session_id)]

    @app.get("/", response_class=HTMLResponse)
    def page() -> str:
        return resources.files("bpp.benchmarks.draw.studio").joinpath("page.html").read_text(encoding="utf-8")

    @app.post("/api/session", dependencies=auth)
    def new_session() -> dict:
        return {"session": studio.new_session(), "limits": studio.limits.__dict__}

    @app.delete("/api/session", dependencies=auth)
    def end_session(sid: SessionId) -> dict:
        studio.end_session(sid)
        return {"session": sid, "ended": True}

    @app.get("/api/checkpoints", dependencies=auth)
    def checkpoints() -> list[dict]:
        return [c.public() for c in studio.checkpoints.values()]

    @app.get("/api/stored", dependencies=auth)
    def stored() -> list[dict]:
        return studio.stored_prompts()

    @app.post("/api/prompts", dependencies=auth)
    def add_prompt(body: PromptRequest, sid: SessionId) -> dict:
        if isinstance(body, DrawnPrompt):
            prompt = studio.add_drawn_prompt(sid, body.samples, body.board_angle)
        elif isinstance(body, StrokesPrompt):
            prompt = studio.add_strokes_prompt(sid, body.strokes, body.board_angle, body.seed)
        elif isinstance(body, FilePrompt):
            prompt = studio.add_file_prompt(sid, body.name, body.text, body.board_angle, body.seed)
        else:
            prompt = studio.add_stored_prompt(sid, body.task, body.demo)
        return prompt.public()

    @app.get("/api/prompts/{pid}/task.json", dependencies=auth)
    def task_file(pid: str, sid: SessionId) -> JSONResponse:
        headers = {"Content-Disposition": f'attachment; filename="studio-{pid[:16]}.json"'}
        return JSONResponse(studio.prompt_task_file(sid, pid), headers=headers)

    @app.post("/api/rollouts", dependencies=auth)
    def start(body: RolloutRequest, sid: SessionId) -> dict:
        rollout = studio.start_rollout(
            sid, body.prompt_id, body.checkpoint_id, body.board_angle, body.seed, body.max_steps, body.frames
        )
        return rollout.public()

    @app.get("/api/rollouts/{rid}", dependencies=auth)
    def status(rid: str, sid: SessionId) -> dict:
        return studio.rollout(sid, rid).public()

    @app.delete("/api/rollouts/{rid}", dependencies=auth)
    def stop(rid: str, sid: SessionId) -> dict:
        return studio.stop_rollout(sid, rid).public()

    @app.get("/api/rollouts/{rid}/events", dependencies=auth)
    async def events(
        rid: str,
        sid: SessionId,
        request: Request,
        since: int = Query(default=0, ge=0),
        last_event_id: Annotated[str | None, Header()] = None,
    ):
        rollout = studio.rollout(sid, rid)  # 404 before the stream starts
        if last_event_id and last_event_id.isdigit():  # a browser reconnecting resumes after what it has
            since = max(since, int(last_event_id) + 1)

        async def stream():
            sent, ended = since, False
            try:
                while True:
                    rollout.last_read = time.monotonic()
                    for event in rollout.events[sent:]:
                        yield f"id: {sent}\ndata: {json.dumps(event)}\n\n"
                        sent += 1
                        ended = ended or event["type"] == "end"
                    if ended:
                        rollout.drop_frames()  # sent; a finished rollout keeps its events without them
                        return
                    if await request.is_disconnected():
                        return
                    await asyncio.sleep(0.02)
            finally:
                if not ended:  # the reader went away (or the server stops): stop drawing for nobody
                    rollout.stop.set()

        return StreamingResponse(stream(), media_type="text/event-stream", headers={"Cache-Control": "no-store"})

    @app.get("/api/rollouts/{rid}/episode.json", dependencies=auth)
    def episode(rid: str, sid: SessionId) -> JSONResponse:
        headers = {"Content-Disposition": f'attachment; filename="rollout-{rid[:16]}.json"'}
        return JSONResponse(studio.episode(sid, rid), headers=headers)

    @app.get("/api/rollouts/{rid}/episode.{fmt}", dependencies=auth)
    def animation(rid: str, fmt: Literal["gif", "mp4"], sid: SessionId) -> FileResponse:
        path = media / f"{secrets.token_hex(8)}.{fmt}"
        with renders:  # rendering is CPU work: a few at a time
            studio.animation(sid, rid, path)
        return FileResponse(
            path, filename=f"rollout-{rid[:16]}.{fmt}", background=BackgroundTask(path.unlink, missing_ok=True)
        )

    app.add_middleware(_LimitBody, limit=studio.limits.max_body_bytes)
    return app
