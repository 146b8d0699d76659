"""The fake sensors: ASCII level stream, Modbus RTU level, A&D and MT-SICS balances."""

from __future__ import annotations

import struct

from dipnet.rig import sensors
from dipnet.rig.fake.device import Device


class LevelDevice(Device):
    """An ASCII level sensor: streams lines, or answers a query (``SensorFormat.level_query``)."""

    def on_open(self) -> None:
        fmt = self.world.sensor_format
        self.streaming = fmt.level_query is None
        self.term = fmt.level_terminator.encode("ascii").decode("unicode_escape").encode("ascii")

    def stream_line(self) -> None:
        value, stable = self.world.read("level_mm")
        self.emit(self.world.sensor_format.level_format.format(value=value), terminator=self.term)

    def parse_input(self) -> None:
        query = self.world.sensor_format.level_query
        if query is None:
            self._inbuf.clear()
            return
        q = query.encode("ascii").decode("unicode_escape").encode("ascii")
        while q in self._inbuf:
            del self._inbuf[:self._inbuf.index(q) + len(q)]
            self.stream_line()


def crc16(data: bytes) -> int:
    """Modbus CRC-16 (polynomial 0xA001 reflected, initial 0xFFFF) of ``data`` (pure)."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def with_crc(body: bytes) -> bytes:
    """``body`` followed by its CRC, low byte first (a Modbus RTU frame)."""
    return body + struct.pack("<H", crc16(body))


class ModbusDevice(Device):
    """A Modbus RTU slave holding the level in its registers (function 0x03 only)."""

    def parse_input(self) -> None:
        fmt = self.world.sensor_format
        while len(self._inbuf) >= 8:
            frame, self._inbuf = bytes(self._inbuf[:8]), self._inbuf[8:]
            if crc16(frame) != 0 or frame[0] != fmt.modbus_slave:
                continue  # a real slave stays silent on bad frames
            _, function, address, count = struct.unpack(">BBHH", frame[:6])
            if function != 0x03:
                self.emit(with_crc(bytes([frame[0], function | 0x80, 1])))
                continue
            words = sensors.DATA_TYPES[fmt.modbus_data_type][0]
            if address != fmt.modbus_address or count != words:
                self.emit(with_crc(bytes([frame[0], 0x83, 2])))
                continue
            value, _ = self.world.read("level_mm")
            regs = sensors.encode_registers(value / fmt.modbus_scale, fmt.modbus_data_type, fmt.modbus_word_order)
            self.emit(with_crc(struct.pack(f">BBB{count}H", frame[0], 3, 2 * count, *regs)))


class BalanceDevice(Device):
    """A balance under the tank, A&D (``Q``) or MT-SICS (``S``/``SI``) style."""

    style = "ad"

    def parse_input(self) -> None:
        dec = self.world.sensor_format.balance_decimals
        for line in self.lines():
            cmd = line.strip().upper()
            if not cmd:
                continue
            value, stable = self.world.read("mass_g")
            if self.style == "ad":
                if cmd not in ("Q", "S"):
                    self.emit("EC,E01")
                    continue
                self.emit(f"{'ST' if stable else 'US'},{value:+0{9}.{dec}f}  g")
            elif cmd in ("S", "SI"):
                self.emit(f"S {'S' if stable else 'D'} {value:>10.{dec}f} g")
            else:
                self.emit("ES")


class SicsDevice(BalanceDevice):
    style = "sics"
