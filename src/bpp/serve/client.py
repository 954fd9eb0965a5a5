"""Robot-side clients of a policy server: openpi's ``WebsocketClientPolicy`` where installed, else a small client of
the same protocol (:class:`PolicyClient`), and :func:`connect` choosing between them.

Nothing here imports torch: the robot side needs only numpy and the websocket client.
"""

from __future__ import annotations

import importlib.util
import inspect
from typing import Any

from bpp.serve.wire import pack, unpack


class ServerError(RuntimeError):
    """The server refused a request (its text reply is the message), as openpi's client raises it."""


class PolicyClient:
    """A minimal client of the protocol of :mod:`bpp.serve.server` (and of openpi's servers): the same calls as
    openpi's ``WebsocketClientPolicy`` (``infer``, ``get_server_metadata``, ``reset``), plus ``close``."""

    def __init__(self, url: str, api_key: str | None = None, timeout: float = 60.0):
        # websockets: the serve extra
        from websockets.sync.client import connect as ws_connect

        headers = {"Authorization": f"Api-Key {api_key}"} if api_key else None
        self.url = url if url.startswith("ws") else f"ws://{url}"
        self._ws = ws_connect(
            self.url,
            compression=None,
            max_size=None,
            additional_headers=headers,
            open_timeout=timeout,
            proxy=None,  # a robot talks to its server directly, whatever proxy the environment names
            **({"legacy": True} if "legacy" in inspect.signature(ws_connect).parameters else {}),
        )
        self._metadata = unpack(self._ws.recv(timeout))
        self.timeout = timeout

    def get_server_metadata(self) -> dict:
        return self._metadata

    def infer(self, obs: dict) -> dict:
        self._ws.send(pack(obs))
        reply = self._ws.recv(self.timeout)
        if isinstance(reply, str):
            raise ServerError(f"Error in inference server:\n{reply}")
        return unpack(reply)

    def reset(self) -> None:
        """Nothing to do on the client (as in openpi's): a new episode is a request with ``"reset": True``."""

    def close(self) -> None:
        self._ws.close()


def openpi_available() -> bool:
    return importlib.util.find_spec("openpi_client") is not None


def connect(url: str, api_key: str | None = None, use_openpi: bool | None = None) -> Any:
    """A client of the server at `url`: openpi's ``WebsocketClientPolicy`` if `use_openpi` (default: if it is
    installed), else :class:`PolicyClient`."""
    if use_openpi is None:
        use_openpi = openpi_available()
    if use_openpi:
        # openpi's client: the robot-side environment only
        from openpi_client.websocket_client_policy import WebsocketClientPolicy

        return WebsocketClientPolicy(url if url.startswith("ws") else f"ws://{url}", api_key=api_key)
    return PolicyClient(url, api_key)


def close(client: Any) -> None:
    """Close either kind of client (openpi's keeps its socket in ``_ws``)."""
    ws = getattr(client, "_ws", None)
    if ws is not None:
        ws.close()
