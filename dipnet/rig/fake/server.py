"""The fake rig's devices over TCP for other processes; ``python -m dipnet.rig.fake``."""

from __future__ import annotations

import argparse
import socket
import threading
import time

from dipnet.rig.fake.device import Device
from dipnet.rig.fake.grbl import GrblDevice
from dipnet.rig.fake.marlin import MarlinDevice
from dipnet.rig.fake.sensors import BalanceDevice, LevelDevice, ModbusDevice, SicsDevice
from dipnet.rig.fake.world import DEVICES, FakeRig

_DEVICE_CLASSES = {"grbl": GrblDevice, "marlin": MarlinDevice, "level": LevelDevice, "modbus": ModbusDevice,
                   "ad": BalanceDevice, "sics": SicsDevice}


def make_device(world: FakeRig, kind: str) -> Device:
    """A new link to ``world``'s device ``kind`` (one of :data:`DEVICES`)."""
    if kind not in _DEVICE_CLASSES:
        raise ValueError(f"unknown fake device {kind!r}; choose one of {DEVICES}")
    return _DEVICE_CLASSES[kind](world)


# ============================================================================ TCP server
class FakeServer:
    """TCP servers on ``host`` bridging sockets to devices of one world (one client each at a time).

    Attributes:
        urls: ``{device: "socket://host:port"}``.
    """

    def __init__(self, world: FakeRig, devices=("grbl", "level"), host: str = "127.0.0.1", ports=None,
                 stream_interval_s: float = 0.01) -> None:
        self.world, self.host, self.stream_interval_s = world, host, float(stream_interval_s)
        self.urls: dict[str, str] = {}
        self._stop = threading.Event()
        self._threads = []
        self._sockets = []
        ports = dict(ports or {})
        for kind in devices:
            srv = socket.create_server((host, int(ports.get(kind, 0))))
            srv.settimeout(0.05)
            self._sockets.append(srv)
            self.urls[kind] = f"socket://{host}:{srv.getsockname()[1]}"
            thread = threading.Thread(target=self._serve, args=(srv, kind), daemon=True, name=f"fakerig-{kind}")
            thread.start()
            self._threads.append(thread)

    def _serve(self, srv: socket.socket, kind: str) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = srv.accept()
            except (socket.timeout, OSError):
                continue
            with conn:
                conn.settimeout(0.002)
                device = make_device(self.world, kind)
                streaming, device.streaming = device.streaming, False
                last = 0.0
                while not self._stop.is_set() and not device.dead:
                    try:
                        data = conn.recv(4096)
                        if not data:
                            break
                        device.receive(data)
                    except socket.timeout:
                        pass
                    except OSError:
                        break
                    now = time.monotonic()
                    if streaming and now - last >= self.stream_interval_s:
                        device.stream_line()
                        last = now
                    out = device.take(4096, 0.0)
                    try:
                        while out:
                            conn.sendall(out)
                            out = device.take(4096, 0.0)
                    except OSError:
                        break

    def close(self) -> None:
        self._stop.set()
        for s in self._sockets:
            s.close()
        for t in self._threads:
            t.join(timeout=1.0)

    def __enter__(self) -> "FakeServer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def serve(world: FakeRig, devices=("grbl", "level"), host: str = "127.0.0.1", ports=None) -> FakeServer:
    """Start :class:`FakeServer` for ``world``; ``server.urls`` holds the ``socket://`` URLs."""
    return FakeServer(world, devices, host, ports)


def main(argv=None) -> None:
    """``python -m dipnet.rig.fake MESH [--radius R] [--devices grbl,level] [--port P]``."""
    parser = argparse.ArgumentParser(prog="python -m dipnet.rig.fake",
                                     description="Serve a fake dipping rig over TCP (socket:// URLs).")
    parser.add_argument("mesh", help="mesh file of the object")
    parser.add_argument("--radius", type=float, default=40.0, help="object radius (mm)")
    parser.add_argument("--devices", default="grbl,level", help=f"comma-separated, from {','.join(DEVICES)}")
    parser.add_argument("--port", type=int, default=0, help="first TCP port (0: any free ports)")
    parser.add_argument("--latency", type=float, default=0.0, help="reply latency (s)")
    parser.add_argument("--move-s", type=float, default=0.0, help="duration of every move (s)")
    args = parser.parse_args(argv)
    kinds = [k.strip() for k in args.devices.split(",") if k.strip()]
    ports = {k: (args.port + i if args.port else 0) for i, k in enumerate(kinds)}
    world = FakeRig(args.mesh, radius=args.radius, latency_s=args.latency, move_s=args.move_s)
    with serve(world, kinds, ports=ports) as server:
        for kind, url in server.urls.items():
            print(f"{kind}: {url}", flush=True)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
