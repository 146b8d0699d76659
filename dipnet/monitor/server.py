"""The monitor's web server: a read-only page on 127.0.0.1, pushed by server-sent events.

:class:`Monitor` follows one raw scan (:mod:`dipnet.monitor.tail`) in a thread, keeps the page's
state (:func:`dipnet.monitor.state.snapshot`) and the newest running reconstruction
(:class:`~dipnet.monitor.worker.ReconWorker`). :func:`make_app` serves (FastAPI):

* ``/``: the page (``dipnet/monitor/page.html``), loading plotly from ``/plotly.min.js`` (the
  installed plotly package, no CDN);
* ``/api/state`` and ``/api/recon``: the current state and reconstruction as JSON;
* ``/api/events``: a server-sent event stream, ``state`` on every change and ``recon`` on every new
  reconstruction.

Nothing the page can send reaches the rig: the server only reads files. Bound to another address than
the loopback, every request must carry the access token (``?token=``, then a cookie) printed at start;
without it the answer is 403.
"""

# (no "from __future__ import annotations": FastAPI reads the endpoints' annotations, e.g. Request, at run time)
import asyncio
import hmac
import secrets
import socket
import threading
import time
from importlib import resources
from pathlib import Path
from typing import Any

from dipnet.core.optional import optional_import
from dipnet.core.strict_json import dumps
from dipnet.monitor.state import snapshot, writer_alive
from dipnet.monitor.tail import JournalTail, ScanTail

LOOPBACK = ("127.0.0.1", "localhost", "::1")
TOKEN_COOKIE = "dipnet_monitor_token"
#: Seconds between two looks at the scan file.
POLL_S = 0.2
#: Seconds after which the state is rebuilt even without new lines (the clock, a scan that died).
REFRESH_S = 1.0


class MonitorError(ValueError):
    """A monitor cannot start (no scan, port in use, ...); the message says what to do."""


def find_scan(run: str | Path, wait: bool = False) -> Path:
    """The raw scan of ``run`` (a run directory holding ``rawscan.jsonl``, or the ``.jsonl`` itself).
    ``wait``: a scan about to start may not have written it yet."""
    run = Path(run)
    path = run if run.suffix == ".jsonl" else run / "rawscan.jsonl"
    if wait or path.is_file():
        return path
    if not run.exists():
        raise MonitorError(f"{run} does not exist: give the run directory of a scan (scans/<name>) "
                           "or its rawscan.jsonl")
    if run.is_file():
        raise MonitorError(f"{run} is a file, not a scan: give the run directory of a scan (scans/<name>) or its "
                           "rawscan.jsonl; a recording (.csv or .jsonl) plays with --replay FILE")
    raise MonitorError(f"{run} holds no scan: expected {path} (written by scripts/scan.py); to watch a recording "
                       "use --replay FILE")


class Monitor:
    """Follows one scan and holds what the page shows.

    Args:
        scan_path: the raw scan file (it may not exist yet).
        replay: the file is written by a :class:`~dipnet.monitor.replay.Replay` (the page says so).
        worker: the running reconstruction, or ``None`` for none.
    """

    def __init__(self, scan_path: str | Path, *, replay: bool = False, worker: Any = None) -> None:
        self.tail, self.journal = ScanTail(scan_path), JournalTail(scan_path)
        self.replay, self.worker = replay, worker
        self.state: dict[str, Any] = {}
        self.recon_payload: dict[str, Any] | None = None
        self.version = self.recon_version = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="monitor-tail", daemon=True)
        self.refresh(force=True)

    def start(self) -> "Monitor":
        if self.worker is not None:
            self.worker.start()
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        if self.worker is not None:
            self.worker.close()

    def refresh(self, force: bool = False) -> bool:
        """Read what is new and rebuild the state if anything changed (or ``force``)."""
        changed = self.tail.poll() | self.journal.poll()
        recon = self.worker is not None and self.worker.latest()
        if recon:
            self.recon_payload = self._recon_payload()
            self.recon_version += 1
        if changed or recon or force:
            result = self.worker.result if self.worker is not None else None
            state = snapshot(self.tail, self.journal, replay=self.replay, alive=writer_alive(self.tail.path),
                             recon=result)
            if self.worker is not None and self.worker.error:
                state["warnings"].append(f"running reconstruction failed {self.worker.error}")
            self.state = state
            self.version += 1
        return bool(changed or recon or force)

    def _recon_payload(self) -> dict[str, Any] | None:
        result = self.worker.result
        if result is None:
            return None
        return {key: result[key] for key in ("version", "n_dips", "seconds", "extent_mm", "resolution", "slices",
                                              "mesh", "uncertainty")}

    def _loop(self) -> None:
        last = time.monotonic()
        while not self._stop.wait(POLL_S):
            due = time.monotonic() - last > REFRESH_S
            if self.refresh(force=due):
                last = time.monotonic()


def page_html() -> str:
    """The page (package data ``dipnet/monitor/page.html``)."""
    return resources.files("dipnet.monitor").joinpath("page.html").read_text(encoding="utf-8")


def make_app(monitor: Monitor, token: str | None = None):
    """The FastAPI app serving ``monitor``; with a ``token`` every request must carry it."""
    from fastapi import FastAPI, Request
    from fastapi.responses import HTMLResponse, JSONResponse, PlainTextResponse, Response, StreamingResponse

    app = FastAPI(title="dipnet scan monitor", docs_url=None, redoc_url=None, openapi_url=None)

    @app.middleware("http")
    async def check_token(request: Request, call_next):
        if token is None:
            return await call_next(request)
        given = request.query_params.get("token") or request.cookies.get(TOKEN_COOKIE) or ""
        if not hmac.compare_digest(given.encode(), token.encode()):
            return PlainTextResponse("403 forbidden: this monitor needs the access token printed when it started "
                                     "(open the printed URL, ...?token=...)", status_code=403)
        response = await call_next(request)
        response.set_cookie(TOKEN_COOKIE, token, httponly=True, samesite="strict")
        return response

    @app.get("/", response_class=HTMLResponse)
    def index() -> str:
        return page_html()

    @app.get("/plotly.min.js")
    def plotly_js() -> Response:
        plotly = optional_import("plotly.offline", "report", "the monitor page")
        return Response(plotly.get_plotlyjs(), media_type="application/javascript",
                        headers={"Cache-Control": "max-age=86400"})

    @app.get("/api/state")
    def state() -> JSONResponse:
        return JSONResponse(monitor.state)

    @app.get("/api/recon")
    def recon() -> JSONResponse:
        return JSONResponse(monitor.recon_payload)

    @app.get("/api/events")
    async def events(request: Request) -> StreamingResponse:
        async def stream():
            seen = seen_recon = -1
            while not await request.is_disconnected():
                if monitor.version != seen:
                    seen = monitor.version
                    yield f"event: state\ndata: {dumps(monitor.state)}\n\n"
                if monitor.recon_version != seen_recon and monitor.recon_payload is not None:
                    seen_recon = monitor.recon_version
                    yield f"event: recon\ndata: {dumps(monitor.recon_payload)}\n\n"
                await asyncio.sleep(0.1)

        return StreamingResponse(stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"})

    return app


def access_token(host: str, token: str | None = None) -> str | None:
    """The access token for ``host``: none on the loopback, else ``token`` or a new random one."""
    return None if host in LOOPBACK else (token or secrets.token_urlsafe(18))


def check_port(host: str, port: int) -> None:
    """Raise :class:`MonitorError` when ``host:port`` cannot be bound (not a port 1-65535, in use, or not
    this machine's)."""
    if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
        raise MonitorError(f"the monitor's port must be 1-65535, got {port!r} (--port / monitor_port=)")
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        try:
            sock.bind((host, port))
        except OSError as exc:
            raise MonitorError(f"cannot serve the monitor on {host}:{port}: {exc.strerror or exc} (another monitor or "
                               "program uses the port? choose another with --port / monitor_port=)") from None


def page_url(host: str, port: int, token: str | None) -> str:
    """The address to open (with the token when there is one)."""
    shown = f"[{host}]" if ":" in host else host
    return f"http://{shown}:{port}/" + (f"?token={token}" if token else "")


def make_server(monitor: Monitor, host: str = "127.0.0.1", port: int = 8765, token: str | None = None):
    """The uvicorn server of :func:`make_app` on ``host:port`` (``run()`` it; ``should_exit = True`` stops it)."""
    import uvicorn

    check_port(host, port)
    config = uvicorn.Config(make_app(monitor, token), host=host, port=port, log_level="warning", lifespan="off",
                            timeout_graceful_shutdown=1)   # the event streams never end by themselves
    return uvicorn.Server(config)


def serve(monitor: Monitor, host: str = "127.0.0.1", port: int = 8765, token: str | None = None) -> None:
    """Serve ``monitor`` until interrupted (uvicorn); ``token`` as :func:`make_app`."""
    make_server(monitor, host, port, token).run()
