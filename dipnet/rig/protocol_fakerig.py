"""pyserial URL handler ``fakerig://<world>/<device>``: a port wired to a :mod:`dipnet.rig.fake` world.

pyserial's ``serial_for_url`` imports ``<package>.protocol_<scheme>`` for every package in
``serial.protocol_handler_packages`` and uses its ``Serial`` class (as ``loop://`` does);
:func:`dipnet.rig.register_url_handlers` adds ``dipnet.rig`` to that list. The module name is
that convention's, not a choice: ``protocol`` here means a pyserial URL scheme.
"""

from __future__ import annotations

import urllib.parse

from serial.serialutil import PortNotOpenError, SerialBase, SerialException


class Serial(SerialBase):
    """A serial port whose other end is a fake device (see :mod:`dipnet.rig.fake`)."""

    def open(self) -> None:
        from dipnet.rig.fake.server import make_device
        from dipnet.rig.fake.world import WORLDS

        if self.is_open:
            raise SerialException("Port is already open.")
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        parts = urllib.parse.urlsplit(self._port)
        if parts.scheme != "fakerig" or not parts.netloc or not parts.path.strip("/"):
            raise SerialException(f"expected fakerig://<world>/<device>, got {self._port!r}")
        if parts.netloc not in WORLDS:
            raise SerialException(f"no fake rig named {parts.netloc!r} is registered (have {sorted(WORLDS)})")
        try:
            self.device = make_device(WORLDS[parts.netloc], parts.path.strip("/"))
        except ValueError as exc:
            raise SerialException(str(exc)) from exc
        self.is_open = True

    def close(self) -> None:
        self.is_open = False
        super().close()

    def _reconfigure_port(self, *args, **kwargs) -> None:
        """Serial settings mean nothing here."""

    def _check(self) -> None:
        if not self.is_open:
            raise PortNotOpenError()
        if self.device.dead:
            raise SerialException(f"{self._port}: device disconnected")

    @property
    def in_waiting(self) -> int:
        self._check()
        return self.device.pending()

    def read(self, size: int = 1) -> bytes:
        self._check()
        data = bytearray()
        timeout = self._timeout
        while len(data) < size:
            chunk = self.device.take(size - len(data), timeout)
            if not chunk:
                break
            data += chunk
            timeout = 0.0  # after the first bytes, return what is ready
        return bytes(data)

    def write(self, data) -> int:
        self._check()
        data = bytes(data)
        self.device.receive(data)
        return len(data)

    def reset_input_buffer(self) -> None:
        self._check()
        self.device.clear_output()

    def reset_output_buffer(self) -> None:
        self._check()

    @property
    def out_waiting(self) -> int:
        return 0

    def _update_break_state(self) -> None:
        pass

    def _update_rts_state(self) -> None:
        pass

    def _update_dtr_state(self) -> None:
        pass

    @property
    def cts(self) -> bool:
        return True

    @property
    def dsr(self) -> bool:
        return True

    @property
    def ri(self) -> bool:
        return False

    @property
    def cd(self) -> bool:
        return True
