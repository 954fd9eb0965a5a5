"""The transport alone: the `websockets` library's own server and client on loopback, no bpp code, a message sent
and a reply of a chosen size received (the anchor a served policy's round trip or an upload is set against). Light
to import: a script that spawns worker processes can use it without loading torch in each."""

from __future__ import annotations

import multiprocessing as mp
import time


def echo_server(reply_bytes: int, ports) -> None:
    """A bare `websockets` server that answers every message with `reply_bytes` bytes (the transport's floor)."""
    from websockets.sync.server import serve  # websockets: the serve extra

    reply = bytes(reply_bytes)

    def handler(connection) -> None:
        for _ in connection:
            connection.send(reply)

    with serve(handler, "127.0.0.1", 0, compression=None, max_size=None) as server:
        ports.put(server.socket.getsockname()[1])
        server.serve_forever()


def transport_floor(request_bytes: int, reply_bytes: int, requests: int) -> list[float]:
    """Round trips (ms) of `requests` messages of `request_bytes` to :func:`echo_server` in its own process."""
    from websockets.sync.client import connect  # websockets: the serve extra

    ports: mp.Queue = mp.get_context("spawn").Queue()
    proc = mp.get_context("spawn").Process(target=echo_server, args=(reply_bytes, ports), daemon=True)
    proc.start()
    try:
        with connect(f"ws://127.0.0.1:{ports.get(timeout=60)}", compression=None, max_size=None) as ws:
            message, times = bytes(request_bytes), []
            for _ in range(requests + 2):
                t0 = time.perf_counter()
                ws.send(message)
                ws.recv()
                times.append(1e3 * (time.perf_counter() - t0))
    finally:
        proc.terminate()
        proc.join()
    return times[2:]
