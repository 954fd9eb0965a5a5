"""``bpp serve``: any trained policy behind a websocket that openpi's ``WebsocketClientPolicy`` talks to.

The protocol (binary msgpack frames, :mod:`bpp.serve.wire`):

* On connect the server sends its metadata (:meth:`PolicyServer.metadata`): the method, what it observes (keys,
  shapes, dtypes), its action key and chunk shape, To, Ta, the control rate it was trained at and the prompts it
  offers.
* ``infer(obs)``: ``obs`` holds every key the policy observes, either one step (the shape in the metadata) or the
  k steps since the last request with a leading time axis (oldest first), and optionally ``"prompt"`` (a prompt
  id, see :class:`bpp.serve.prompts.PromptLibrary`; for a Language policy also instruction text, as openpi's
  servers read it), ``"reset"`` (True: a new episode) and ``"seed"`` (the new episode's noise seed, default 0).
  The first request of a connection names a prompt; naming a different one, or ``reset``, starts a new episode:
  the prompt is encoded once, the observation history and the noise generator start over. The reply is
  ``{"actions": (T - To + 1, A), ...}``: the predicted chunk from the current step on, of which ``bpp eval``
  executes the first ``n_action_steps`` before asking again. A client that sends every step's observation and
  replans after ``n_action_steps`` gets exactly the actions ``bpp eval`` computes.
* ``infer({"upload": demonstration})`` stores a demonstration (``{"obs": ..., "action": ..., "instruction": ...}``)
  and replies ``{"prompt": handle}``, an id any client may then use while the upload is kept (see
  :mod:`bpp.serve.prompts`: while its connection is open, an episode runs it, or it is the newest).

Every field of a request is checked before anything changes (observations by
:func:`bpp.data.arrays.check_array`: shape, dtype kind, finite values within a bound of the training range).
A request the server cannot use gets a text frame naming the field and what was wrong (openpi's client raises it as
a RuntimeError) and the connection stays open with the session unchanged; a frame that is not a message of this
protocol closes the connection; a client that vanishes is let go quietly. Each connection has its own episode;
requests that arrive together are answered by one batched inference call.
"""

from __future__ import annotations

import asyncio
import hmac
import logging
import queue
import threading
import time
import traceback
from collections import Counter, deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from http import HTTPStatus
from typing import Any

import numpy as np
import torch

from bpp import __version__
from bpp.data.arrays import as_array, check_array
from bpp.errors import UserError
from bpp.network import listen, urls
from bpp.policies.agent import history_at, predict_chunks
from bpp.policies.validation import feature_bounds
from bpp.serve.prompts import PromptLibrary
from bpp.serve.wire import WireError, pack, unpack
from bpp.utils import to_torch

log = logging.getLogger("bpp.serve")

CONTROL_KEYS = ("prompt", "reset", "seed")
"""Request fields besides observations."""
MAX_STEPS_PER_REQUEST = 64
"""Observation steps one request may carry (a client replanning every Ta steps sends Ta)."""


class RequestError(UserError):
    """A request the server cannot use; the reply names the field and what was expected."""


@dataclass(frozen=True)
class ServerLimits:
    """What one client may ask of the server."""

    max_message_bytes: int = 64 * 2**20
    """Largest frame accepted (larger ones close the connection with code 1009); an upload must fit in one."""
    max_clients: int = 64
    """Connections served at once; more are refused with HTTP 503."""
    max_batch: int = 32
    """Requests answered by one inference call."""
    batch_wait_s: float = 0.0
    """How long the model waits after a request for others to join its batch (0: it takes those already
    waiting, which under load is all of them)."""


# ----------------------------------------------------------------------------------------------- sessions
@dataclass(eq=False)
class Session:
    """One connection's episode: its prompt, encoded context, noise generator and observation history."""

    peer: str
    prompt: str | None = None
    context: Any = None
    generator: torch.Generator | None = None
    history: deque = field(default_factory=deque)
    steps: int = 0
    requests: int = 0

    def start(self, prompt: str, context: Any, seed: int, history_length: int, device) -> None:
        self.prompt, self.context = prompt, context
        self.generator = torch.Generator(device).manual_seed(seed)
        self.history = deque(maxlen=history_length)
        self.steps = 0

    def push(self, steps: list[dict[str, np.ndarray]]) -> None:
        """Append observations in order; the first of an episode fills the history, as the agent does."""
        for obs in steps:
            if not self.history:
                self.history.extend([obs] * (self.history.maxlen - 1))
            self.history.append(obs)
            self.steps += 1


# ----------------------------------------------------------------------------------------------- the model thread
@dataclass(eq=False)
class _Job:
    future: asyncio.Future
    session: Session | None = None
    call: Callable | None = None
    submitted: float = field(default_factory=time.perf_counter)


class ModelWorker:
    """The one thread that touches the model (and renders prompts): calls run one at a time, inference requests
    waiting together run as one batch."""

    def __init__(self, model, limits: ServerLimits):
        self.model, self.limits = model, limits
        self.offsets = model.data_spec().obs_offsets
        self.jobs: queue.Queue[_Job | None] = queue.Queue()
        self.thread = threading.Thread(target=self._loop, name="bpp-model", daemon=True)
        self.batch_sizes: Counter[int] = Counter()
        """Inference calls per batch size (counts, not a log: bounded however long the server runs)."""
        self.thread.start()

    def call(self, fn: Callable, *args) -> asyncio.Future:
        future = asyncio.get_running_loop().create_future()
        self.jobs.put(_Job(future, call=lambda: fn(*args)))
        return future

    def infer(self, session: Session) -> asyncio.Future:
        future = asyncio.get_running_loop().create_future()
        self.jobs.put(_Job(future, session=session))
        return future

    def stop(self) -> None:
        self.jobs.put(None)
        self.thread.join(timeout=10)

    def _loop(self) -> None:
        torch.set_grad_enabled(False)
        while True:
            job = self.jobs.get()
            if job is None:
                return
            if job.call is not None:
                _settle(job.future, job.call)
                continue
            if self.limits.batch_wait_s:
                time.sleep(self.limits.batch_wait_s)
            batch, later = [job], []
            while len(batch) < self.limits.max_batch:
                try:
                    other = self.jobs.get_nowait()
                except queue.Empty:
                    break
                if other is None:
                    self.jobs.put(None)
                    break
                (later if other.call is not None else batch).append(other)
            batch = [j for j in batch if not j.future.cancelled()]
            if len(batch) == 1:
                self._run_batch(batch, batch[0].session.context)
            elif batch:
                try:
                    merged = self.model.merge_contexts([j.session.context for j in batch])
                except Exception:  # noqa: BLE001 - contexts that do not join (a bug) are served one at a time
                    log.error("could not join contexts into one batch:\n%s", traceback.format_exc())
                    merged = None
                if merged is not None:
                    self._run_batch(batch, merged)
                else:  # contexts with per-rollout state (ICRT's cache) are served one at a time
                    for j in batch:
                        self._run_batch([j], j.session.context)
            for other in later:
                _settle(other.future, other.call)

    def _run_batch(self, group: list[_Job], context) -> None:
        start = time.perf_counter()
        try:
            sessions = [j.session for j in group]
            read = [history_at(s.history, self.offsets) for s in sessions]
            history = {k: np.stack([np.stack([o[k] for o in r]) for r in read]) for k in self.model.obs_keys()}
            # with the prompt attention, as `bpp eval` records it: the same arithmetic, so the same actions
            chunks, attention = predict_chunks(
                self.model, history, context, [s.generator for s in sessions], return_attention=True
            )
        except Exception as err:  # noqa: BLE001 - every waiting client gets the error, the server lives on
            for job in group:
                _resolve(job.future, exception=err)
            return
        elapsed = time.perf_counter() - start
        self.batch_sizes[len(group)] += 1
        for i, job in enumerate(group):
            timing = {"infer_ms": 1e3 * elapsed, "queue_ms": 1e3 * (start - job.submitted), "batch": len(group)}
            weights = None
            if attention is not None:  # (n_chunks + 1,) of this client's own prompt (a batch pads to its longest)
                weights = attention[i, : getattr(job.session.context, "num_chunks", attention.shape[1] - 1) + 1]
            _resolve(job.future, result=(chunks[i], weights, timing))


def _settle(future: asyncio.Future, call: Callable) -> None:
    try:
        _resolve(future, result=call())
    except Exception as err:  # noqa: BLE001 - passed to the waiting coroutine
        _resolve(future, exception=err)


def _resolve(future: asyncio.Future, result=None, exception: BaseException | None = None) -> None:
    def settle():
        if future.cancelled() or future.done():
            return  # the client left: its answer goes nowhere
        if exception is not None:
            future.set_exception(exception)
        else:
            future.set_result(result)

    future.get_loop().call_soon_threadsafe(settle)


# ----------------------------------------------------------------------------------------------- the server
class PolicyServer:
    """Serves one model to many clients; see the module docstring for the protocol.

    Args:
        model: a policy model (any method), in eval mode.
        library: the prompts offered.
        info: metadata describing where the model comes from (checkpoint, benchmark, control rate), sent to clients.
        token: when set, every connection must send ``Authorization: Api-Key <token>`` (openpi's client's
            ``api_key``); compared in constant time.
        n_action_steps: the Ta reported to clients (default: the model's).
    """

    def __init__(
        self,
        model,
        library: PromptLibrary,
        info: Mapping | None = None,
        token: str = "",
        limits: ServerLimits = ServerLimits(),
        device: str | torch.device = "cpu",
        n_action_steps: int | None = None,
    ):
        self.device = torch.device(device)
        self.model = model.to(self.device).eval()
        self.library, self.info, self.limits = library, dict(info or {}), limits
        self._token = token.encode()
        h = model.cfg.horizons
        self.n_obs_steps, self.horizon = h.n_obs_steps, h.horizon
        self.n_action_steps = n_action_steps or h.n_action_steps
        model.check_action_steps(self.n_action_steps)
        self.spec = model.data_spec()
        self.obs_keys = list(model.obs_keys())
        self.image_keys = set(self.spec.image_keys)
        self.widths = {k: model.normalizer.width(k) for k in self.obs_keys if k not in self.image_keys}
        self.step_shapes = {k: tuple(v["shape"]) for k, v in self.observation_shapes().items()}
        """Each observation key's per-step shape, which every request is checked against."""
        self.bounds = {k: feature_bounds(model.normalizer, k) for k in self.widths}
        """The values each low-dimensional key may take (beyond them a fault, not a reading)."""
        self.worker = ModelWorker(self.model, limits)
        self.clients = 0
        self.served = 0

    # ------------------------------------------------------------------ description
    def observation_shapes(self) -> dict[str, dict]:
        s = self.spec.image_size
        return {
            k: {"shape": [s, s, 3], "dtype": "uint8"}
            if k in self.image_keys
            else {"shape": [self.widths[k]], "dtype": "float32"}
            for k in self.obs_keys
        }

    def metadata(self) -> dict:
        start = self.n_obs_steps - 1
        return {
            "server": "bpp",
            "bpp_version": __version__,
            **self.info,
            "observation": self.observation_shapes(),
            "action": {"key": self.spec.action_key, "shape": [self.horizon - start, self.model.action_dim]},
            "n_obs_steps": self.n_obs_steps,
            "n_action_steps": self.n_action_steps,
            "horizon": self.horizon,
            "context": self.spec.context,
            "prompts": self.library.describe(),
            "max_message_bytes": self.limits.max_message_bytes,
            "max_steps_per_request": MAX_STEPS_PER_REQUEST,
            "max_uploads_per_client": self.library.max_uploads_per_client,
            "max_upload_bytes": self.library.max_upload_bytes,
            "request": (
                "observation keys (one step, or k steps since the last request with a leading time axis), "
                "'prompt' (a prompt id, or instruction text for a Language policy; required to start), "
                "'reset' (bool), 'seed' (int); or {'upload': demonstration}"
            ),
        }

    # ------------------------------------------------------------------ validation
    def parse_observations(self, message: Mapping) -> list[dict[str, np.ndarray]]:
        """A request's observation fields -> the steps they hold, oldest first; RequestError if any is wrong."""
        unknown = sorted(map(str, set(message) - set(self.obs_keys) - set(CONTROL_KEYS)))
        if unknown:
            raise RequestError(
                f"unknown request fields {unknown}; this policy observes {self.obs_keys} and takes {list(CONTROL_KEYS)}"
            )
        missing = [k for k in self.obs_keys if k not in message]
        if missing:
            raise RequestError(f"observation lacks {missing}; this policy observes {self.obs_keys}")
        arrays, count = {}, None
        for key in self.obs_keys:
            value = self.check_observation(key, message[key])
            if count is not None and len(value) != count:
                raise RequestError(
                    f"observation keys carry different numbers of steps ({count} and {len(value)} for {key!r})"
                )
            count = len(value)
            arrays[key] = value
        return [{k: v[i] for k, v in arrays.items()} for i in range(count)]

    def check_observation(self, key: str, value: Any) -> np.ndarray:
        """Observation `key` of a request -> its steps (k, *step shape) as the model takes them: uint8 images,
        float32 features within :attr:`bounds`; RequestError naming the key and the problem otherwise."""
        shape, name = self.step_shapes[key], f"observation {key!r}"
        dims = ", ".join(map(str, shape))
        expected = f"{shape} (one step) or (k, {dims}) with 1 <= k <= {MAX_STEPS_PER_REQUEST}"
        value = as_array(name, value, RequestError)
        if value.shape == shape:
            value = value[None]
        if key in self.image_keys:
            steps = check_array(name, value, (None, *shape), np.uint8, expected=expected, error=RequestError)
        else:
            steps = check_array(
                name, value, (None, *shape), np.float32, bounds=self.bounds[key], expected=expected, error=RequestError
            )
        if not 1 <= len(steps) <= MAX_STEPS_PER_REQUEST:
            raise RequestError(f"{name} must have shape {expected}, got {steps.shape}")
        return steps

    @staticmethod
    def parse_control(message: Mapping) -> tuple[Any, bool, int]:
        prompt = message.get("prompt")
        if prompt is not None and not isinstance(prompt, str | int | np.integer) or isinstance(prompt, bool):
            raise RequestError(
                f"'prompt' must be a prompt id (string or episode number) or, for a Language policy, instruction "
                f"text, got {type(prompt).__name__}"
            )
        reset = message.get("reset", False)
        if not isinstance(reset, bool | np.bool_):
            raise RequestError(f"'reset' must be true or false, got {reset!r}")
        seed = message.get("seed", 0)
        if not isinstance(seed, int | np.integer) or isinstance(seed, bool) or not 0 <= int(seed) < 2**63:
            raise RequestError(f"'seed' must be a non-negative integer, got {seed!r}")
        return prompt, bool(reset), int(seed)

    # ------------------------------------------------------------------ requests
    async def handle(self, session: Session, message: Any) -> dict:
        """One request of `session` -> its reply (RequestError for a request it cannot use, session unchanged)."""
        received = time.perf_counter()
        if not isinstance(message, Mapping):
            raise RequestError(f"a request must be a map, got {type(message).__name__}")
        if "upload" in message:
            if len(message) != 1:
                raise RequestError("an upload request holds only 'upload'")
            handle = await self.worker.call(self.library.upload, message["upload"], session)
            return {"prompt": handle}
        steps = self.parse_observations(message)
        prompt, reset, seed = self.parse_control(message)
        if session.prompt is None and prompt is None:
            raise RequestError("the first request must name a 'prompt' (see the metadata's 'prompts')")
        entry = await self.worker.call(self.library.get, prompt) if prompt is not None else None
        if reset or (entry is not None and entry.id != session.prompt):
            entry = entry or await self.worker.call(self.library.get, session.prompt)
            context = await self.worker.call(self._encode, entry.context)
            session.start(entry.id, context, seed, self.spec.history_length, self.device)
            self.library.run(session, entry.id)
        session.push(steps)
        chunk, attention, timing = await self.worker.infer(session)
        session.requests += 1
        self.served += 1
        start = self.n_obs_steps - 1
        reply = {
            "actions": chunk[start:],
            "n_action_steps": self.n_action_steps,
            "prompt": session.prompt,
            "episode_step": session.steps - 1,
            "server_timing": {**timing, "total_ms": 1e3 * (time.perf_counter() - received)},
        }
        if attention is not None:
            reply["attention"] = attention.astype(np.float32)
        return reply

    def _encode(self, context: Mapping):
        batch = self.model.validate_context(context)
        return self.model.encode_context(to_torch(batch, self.device))

    # ------------------------------------------------------------------ websocket plumbing
    def authorize(self, connection, request):
        """websockets' process_request hook: the token check and the connection limit, before the handshake."""
        if self._token:
            given = request.headers.get("Authorization", "").encode()
            if not hmac.compare_digest(given, b"Api-Key " + self._token):
                log.warning("refused %s: missing or wrong token", connection.remote_address)
                return connection.respond(
                    HTTPStatus.UNAUTHORIZED, "missing or wrong token (Authorization: Api-Key ...)\n"
                )
        if self.clients >= self.limits.max_clients:
            return connection.respond(
                HTTPStatus.SERVICE_UNAVAILABLE, f"server full ({self.limits.max_clients} clients)\n"
            )
        return None

    async def connection(self, ws) -> None:
        """One client's connection, from the metadata to its close; its uploads are let go when it ends."""
        # websockets: the serve extra
        from websockets.exceptions import ConnectionClosed

        peer = ":".join(map(str, ws.remote_address[:2])) if ws.remote_address else "?"
        session = Session(peer)
        self.clients += 1
        log.info("client %s connected (%d now)", peer, self.clients)
        try:
            await ws.send(pack(self.metadata()))
            async for frame in ws:
                if isinstance(frame, str):
                    await ws.send("bpp server: requests are binary msgpack frames, not text; closing")
                    await ws.close(1003, "text frame")
                    return
                try:
                    message = unpack(frame)
                except WireError as err:
                    await ws.send(f"bpp server: {err}; closing")
                    await ws.close(1007, "not a msgpack message")
                    return
                try:
                    reply = await self.handle(session, message)
                except UserError as err:  # the client's mistake: say so, keep the connection
                    await ws.send(f"bpp server: {err}")
                    continue
                except Exception as err:  # noqa: BLE001 - a bug: log it, tell the client, close this connection
                    log.error("request of %s failed:\n%s", peer, traceback.format_exc())
                    await ws.send(f"bpp server: internal error ({type(err).__name__}, logged by the server); closing")
                    await ws.close(1011, "internal error")
                    return
                await ws.send(pack(reply))
        except ConnectionClosed as closed:  # the client went away without closing (or mid-reply): nothing to tell
            log.info("client %s vanished (%s)", peer, closed)
        finally:
            self.clients -= 1
            self.library.release(session)
            log.info("client %s left after %d requests (%d now)", peer, session.requests, self.clients)

    async def serve(self, host: str, port: int, ready: Callable[[int], None] | None = None, stop=None) -> None:
        """Serve until `stop` (an asyncio.Event) is set, or forever; `ready(port)` once listening (a UserError naming
        --host or --port if it cannot listen)."""
        # websockets: the serve extra
        from websockets.asyncio.server import serve

        async with serve(
            self.connection,
            sock=listen(host, port),
            process_request=self.authorize,
            max_size=self.limits.max_message_bytes,
            compression=None,
        ) as server:
            bound = next(iter(server.sockets)).getsockname()[1]
            if ready is not None:
                ready(bound)
            await (stop.wait() if stop is not None else asyncio.Future())

    def close(self) -> None:
        self.worker.stop()


class ServerThread:
    """A server running in a background thread (tests, benchmarks, notebooks): ``with ServerThread(server) as
    url: ...``."""

    def __init__(self, server: PolicyServer, host: str = "127.0.0.1", port: int = 0):
        self.server, self.host, self.port = server, host, port
        self._ready = threading.Event()
        self._error: BaseException | None = None

    def __enter__(self) -> str:
        self.loop = asyncio.new_event_loop()
        self.stop = asyncio.Event()

        def run():
            asyncio.set_event_loop(self.loop)
            try:
                self.loop.run_until_complete(self.server.serve(self.host, self.port, self._bound, self.stop))
            except BaseException as err:  # noqa: BLE001 - reported to the thread that waits for readiness
                self._error = err
                self._ready.set()

        self.thread = threading.Thread(target=run, name="bpp-serve", daemon=True)
        self.thread.start()
        self._ready.wait(30)
        if self._error is not None:
            raise self._error
        return urls("ws", self.host, self.port)[-1]  # loopback, for a wildcard host

    def _bound(self, port: int) -> None:
        self.port = port
        self._ready.set()

    def __exit__(self, *exc) -> None:
        self.loop.call_soon_threadsafe(self.stop.set)
        self.thread.join(timeout=10)
        self.server.close()
