"""The monitor's server (dipnet.monitor.server): the page and plotly from the package, the state as
JSON and as server-sent events, on 127.0.0.1, the token elsewhere."""

from __future__ import annotations

import json
import socket
import threading
import time
from contextlib import contextmanager

import httpx

from dipnet.monitor.server import Monitor, access_token, make_server


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@contextmanager
def running(monitor: Monitor, host: str = "127.0.0.1", token: str | None = None):
    """A real uvicorn server of ``monitor`` in a thread; yields ``(server, base url)``."""
    port = free_port()
    server = make_server(monitor, host, port, token)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        assert time.monotonic() < deadline and thread.is_alive(), "the server did not start"
        time.sleep(0.05)
    try:
        yield server, f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(10)


def test_the_page_state_and_events_of_a_finished_scan(recorded_scan):
    monitor = Monitor(recorded_scan).start()
    try:
        with running(monitor) as (server, url):
            assert server.servers[0].sockets[0].getsockname()[0] == "127.0.0.1"
            page = httpx.get(url + "/").text
            assert '<script src="plotly.min.js">' in page and "cdn" not in page.lower()
            js = httpx.get(url + "/plotly.min.js")
            assert js.status_code == 200 and "plotly" in js.text[:2000].lower()
            state = httpx.get(url + "/api/state").json()
            assert state["mode"] == "finished" and state["n_readings"] == 6 * 28
            with httpx.stream("GET", url + "/api/events", timeout=10) as events:
                lines = events.iter_lines()
                assert next(lines) == "event: state"
                assert json.loads(next(lines)[len("data: "):])["mode"] == "finished"
    finally:
        monitor.close()


def test_bound_elsewhere_every_request_needs_the_token(recorded_scan):
    token = access_token("0.0.0.0")
    assert access_token("127.0.0.1") is None and token and access_token("::1") is None
    monitor = Monitor(recorded_scan)
    with running(monitor, "0.0.0.0", token) as (server, url):
        for path in ("/", "/plotly.min.js", "/api/state", "/api/events"):
            refused = httpx.get(url + path)
            assert refused.status_code == 403 and "access token" in refused.text, path
        assert httpx.get(url + "/api/state", params={"token": "wrong"}).status_code == 403
        with httpx.Client() as browser:                               # the printed URL, then its cookie
            assert browser.get(url + "/", params={"token": token}).status_code == 200
            assert browser.get(url + "/api/state").json()["mode"] == "finished"
