"""Sensors of a dipping rig, one interface: ``read() -> Reading(value, unit, stable)``.

* :class:`LineSensor`: a water-level sensor on an ASCII line stream (a regex matching the whole
  line, with a named group ``value`` and optionally ``unit``; a configurable terminator; streaming,
  or polled with a query string). A line that is not a reading in the sensor's unit (an error
  string such as ``ERR 42``, another unit, a decimal comma) is a failed reading, never a number.
* :class:`ModbusLevelSensor`: a level transducer read over Modbus RTU (function 0x03, read
  holding registers), with register address, data type, word order, scale and offset; the
  frames, CRC and exception replies are ``minimalmodbus``'s, over the pyserial port opened here
  (so ``socket://`` and ``fakerig://`` URLs work too).
* :class:`BalanceSensor`: a laboratory balance under the tank, A&D style (``Q`` ->
  ``ST,+00123.45  g``) or Mettler-Toledo MT-SICS (``SI`` -> ``S S     100.00 g``); values in g.
* :class:`AveragingSensor`: the mean of ``n`` readings, stable only if every reading is and
  their spread is within a tolerance.

The parsers (:func:`parse_ad`, :func:`parse_sics`, :func:`parse_line`, the register codecs
:func:`decode_registers` / :func:`encode_registers`) are pure.
"""

from __future__ import annotations

import re
import struct
import time
from abc import abstractmethod
from types import ModuleType
from typing import NamedTuple

import numpy as np
import serial

from dipnet.core.counts import whole_number
from dipnet.core.flags import checked_flag
from dipnet.core.optional import optional_import
from dipnet.rig.controller import (LineChannel, PortLock, RigDisconnected, RigError, RigTimeout, SerialDevice,
                                   open_channel, open_port, seconds)


def modbus() -> ModuleType:
    """The ``minimalmodbus`` module (the ``rig`` extra), or an ImportError naming that extra."""
    return optional_import("minimalmodbus", extra="rig", purpose="a Modbus level sensor (sensor=modbus)")


class SensorError(RigError):
    """The sensor reported an error (overload, syntax error, Modbus exception, bad frame)."""


class GarbledReply(SensorError):
    """A reply that is not a line of the sensor's protocol at all (a byte lost or flipped on the wire, a reply
    cut short): worth asking again, unlike an error the sensor reports (overload, a wrong mode or unit)."""


class Reading(NamedTuple):
    """One sensor reading: ``value`` in ``unit`` (``"mm"`` or ``"g"``), and its stability flag."""

    value: float
    unit: str
    stable: bool


GRAMS = {"g": 1.0, "kg": 1000.0, "mg": 1e-3}
#: A decimal number, optionally signed and with an exponent (``151.2``, ``-.5``, ``1.5e2``): no decimal
#: comma, no thousands separator.
NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
#: The default level line: a number and its unit (any word, checked against the sensor's ``unit``),
#: optionally after the label ``L=`` (the fake rig's format, ``L=151.234 mm``); the whole line must match.
LEVEL_PATTERN = rf"(?:L=)?\s*(?P<value>{NUMBER})\s*(?P<unit>[a-zA-Z]+)?"


# ----------------------------------------------------------------------------- parsers
def parse_line(line: str, pattern: str | re.Pattern, unit: str = "mm", unit_optional: bool = False) -> Reading:
    """The reading of a level line (pure).

    ``pattern`` must match the whole line (surrounding whitespace ignored); its named group ``value``
    holds the number, an optional group ``unit`` its unit and a non-empty group ``flag`` marks the
    reading unstable. A line in another unit than ``unit``, or without a unit when the pattern has a
    ``unit`` group that did not match and ``unit_optional`` is false, is not a reading.

    Raises:
        SensorError: the line is not a reading in ``unit`` (an error string, another unit, a decimal
            comma, ...); the message quotes the line.
    """
    regex = re.compile(pattern) if isinstance(pattern, str) else pattern
    m = regex.fullmatch(line.strip())
    if m is None:
        raise SensorError(f"not a level reading: {line.strip()!r} does not match {regex.pattern!r}")
    groups = m.groupdict()
    found = groups.get("unit")
    if found is None and "unit" in regex.groupindex and not unit_optional:
        raise SensorError(f"level line {line.strip()!r} has no unit: the sensor is set to read {unit} "
                          f"(unit_optional=true reads a bare number in {unit})")
    if found is not None and found != unit:
        raise SensorError(f"level line {line.strip()!r} is in {found!r}, the sensor is set to read {unit!r}")
    try:
        value = float(groups["value"])
    except (TypeError, ValueError):
        raise SensorError(f"level line {line.strip()!r}: {groups['value']!r} is not a number") from None
    return Reading(value, unit, not groups.get("flag"))


def _grams(value: str, unit: str | None, line: str) -> float:
    """``value`` in ``unit`` as g; :class:`SensorError` quoting ``line`` for a missing or unknown unit."""
    unit = (unit or "").strip()
    if not unit:
        raise GarbledReply(f"balance line {line.strip()!r} has no unit")
    if unit not in GRAMS:
        raise SensorError(f"balance reports unknown unit {unit!r} in {line!r}")
    return float(value) * GRAMS[unit]


def parse_ad(line: str) -> Reading:
    """An A&D balance line ``ST,+00123.45  g`` (``ST`` stable, ``US`` unstable, ``QT`` count,
    ``OL`` overload); value in g (pure)."""
    m = re.fullmatch(rf"\s*(?P<head>ST|US|QT|OL)\s*,\s*(?P<value>{NUMBER})\s*(?P<unit>[a-zA-Z]*)\s*", line)
    if m is None:
        raise GarbledReply(f"not an A&D balance line: {line!r}")
    if m["head"] == "OL":
        raise SensorError(f"balance overload: {line.strip()!r}")
    if m["head"] == "QT":
        raise SensorError(f"balance is in counting mode (QT), expected weighing: {line.strip()!r}")
    return Reading(_grams(m["value"], m["unit"], line), "g", m["head"] == "ST")


def parse_sics(line: str) -> Reading:
    """An MT-SICS ``S``/``SI`` reply ``S S     100.00 g`` (``S`` stable, ``D`` dynamic); errors
    ``S I`` (busy), ``S +``/``S -`` (over/underload), ``ES``/``ET``/``EL`` raise (pure; ``ET``, a transmission
    error, and a reply of no MT-SICS form as :class:`GarbledReply`)."""
    text = line.strip()
    if text == "ET":
        raise GarbledReply("balance rejected the command (ET: transmission error)")
    if text in ("ES", "EL"):
        raise SensorError(f"balance rejected the command ({text}: "
                          f"{ {'ES': 'syntax error', 'ET': 'transmission error', 'EL': 'logical error'}[text]})")
    m = re.fullmatch(rf"S\s+(?P<status>[SDI+\-])(?:\s+(?P<value>{NUMBER})\s*(?P<unit>[a-zA-Z]+))?", text)
    if m is None:
        raise GarbledReply(f"not an MT-SICS weight reply: {line!r}")
    status = m["status"]
    if status in "+-":
        raise SensorError(f"balance {'overload' if status == '+' else 'underload'}: {text!r}")
    if status == "I" or m["value"] is None:
        return Reading(float("nan"), "g", False)  # busy: no value now
    return Reading(_grams(m["value"], m["unit"], line), "g", status == "S")


# ----------------------------------------------------------------------------- Modbus registers
DATA_TYPES = {"uint16": (1, "H"), "int16": (1, "h"), "uint32": (2, "I"), "int32": (2, "i"), "float32": (2, "f")}


def decode_registers(registers: list[int], data_type: str = "int32", word_order: str = "big") -> float:
    """Registers (16-bit, big-endian bytes each) to a number; ``word_order="little"`` puts the
    low word first (pure)."""
    if data_type not in DATA_TYPES:
        raise ValueError(f"data_type must be one of {sorted(DATA_TYPES)}, got {data_type!r}")
    if word_order not in ("big", "little"):
        raise ValueError(f"word_order must be 'big' or 'little', got {word_order!r}")
    words, code = DATA_TYPES[data_type]
    regs = list(registers[:words])
    if word_order == "little":
        regs.reverse()
    return float(struct.unpack(f">{code}", struct.pack(f">{words}H", *regs))[0])


def encode_registers(value: float, data_type: str = "int32", word_order: str = "big") -> list[int]:
    """Inverse of :func:`decode_registers` (integer types round ``value``)."""
    words, code = DATA_TYPES[data_type]
    raw = struct.pack(f">{code}", value if code == "f" else int(round(value)))
    regs = list(struct.unpack(f">{words}H", raw))
    return regs[::-1] if word_order == "little" else regs


# ----------------------------------------------------------------------------- sensors
class Sensor(SerialDevice):
    """A sensor on a pyserial URL. ``read()`` returns one :class:`Reading`."""

    quantity = "level_mm"

    def __init__(self, url: str, *, baudrate: int = 9600, timeout: float = 1.0) -> None:
        self.url = url
        self.baudrate = baudrate
        self.timeout = seconds(timeout, "timeout", "sensor.device")
        self.link: LineChannel | None = None

    def connect(self) -> None:
        self.link = open_channel(self.url, self.terminator_bytes(), self.baudrate)

    def terminator_bytes(self) -> bytes:
        return b"\n"

    def identity(self) -> dict:
        return {"kind": type(self).__name__, "url": self.url, "quantity": self.quantity}

    def _link(self) -> LineChannel:
        if self.link is None:
            raise RigDisconnected(f"sensor {self.url} is not connected: call connect() first")
        return self.link

    @abstractmethod
    def read(self) -> Reading:
        """One reading."""


class LineSensor(Sensor):
    """A level sensor sending ASCII lines.

    Args:
        url: pyserial URL.
        pattern: regex matching a whole line (surrounding whitespace ignored), with a named group
            ``value`` (and optionally ``unit``, ``flag``): see :func:`parse_line`.
        terminator: line terminator (``"\\n"``, ``"\\r"``, ``"\\r\\n"``; escapes accepted).
        query: string sent before each reading (polled sensors); ``None`` for a stream, whose
            stale input is discarded first so the reading is fresh (with the line then in flight, which may
            have lost its start: up to one line period more per reading).
        unit: the unit of the readings (``"mm"``); a line in another unit is not a reading.
        unit_optional: read a line without a unit (the pattern's ``unit`` group empty) in ``unit``.
        max_lines: lines to try before giving up (each line that is not a reading counts).
    """

    def __init__(self, url: str, pattern: str = LEVEL_PATTERN, terminator: str = "\n", query: str | None = None,
                 unit: str = "mm", unit_optional: bool = False, max_lines: int = 5, **options) -> None:
        super().__init__(url, **options)
        self.pattern = re.compile(pattern)
        if "value" not in self.pattern.groupindex:
            raise ValueError(f"sensor pattern {pattern!r} has no named group 'value' (the number): write it "
                             r"as (?P<value>...)")
        if int(max_lines) < 1:
            raise ValueError(f"sensor max_lines must be >= 1, got {max_lines!r}")
        self.terminator = terminator.encode("ascii").decode("unicode_escape")
        if not self.terminator:
            raise ValueError("sensor.device.terminator is empty: give the end of the sensor's lines ('\\n', '\\r' "
                             "or '\\r\\n')")
        self.query = None if query is None else query.encode("ascii").decode("unicode_escape")
        # bool("no") is true: bare numbers were read as mm
        self.unit, self.unit_optional = unit, checked_flag("sensor.device.unit_optional", unit_optional)
        self.max_lines = int(max_lines)

    def terminator_bytes(self) -> bytes:
        return self.terminator.encode("ascii")

    def identity(self) -> dict:
        return {**super().identity(), "pattern": self.pattern.pattern, "query": self.query, "unit": self.unit}

    def read(self) -> Reading:
        link = self._link()
        if self.query is None:
            link.discard_input()
            # the line in flight when the input was dropped has lost its start ('234 mm' of 'L=151.234 mm'), which
            # can still read as a number: drop up to the next terminator, so every line read is whole
            link.read_line(self.timeout)
        else:
            link.write(self.query.encode("ascii"))
        failure, tried = None, 0
        while tried < self.max_lines:
            try:
                line = link.read_line(self.timeout)
            except RigTimeout:
                if failure is None:
                    raise
                break  # a polled sensor answered with something else, and then nothing more
            tried += 1
            try:
                return parse_line(line, self.pattern, self.unit, self.unit_optional)
            except SensorError as exc:  # not a reading (an error string, another unit): try the next line
                failure = exc
        raise SensorError(f"sensor {self.url} gave no reading in {tried} line(s); the last: {failure}")


class BalanceSensor(Sensor):
    """A balance under the tank; readings in g (apparent mass of the displaced water).

    Args:
        url: pyserial URL.
        style: ``"ad"`` (A&D) or ``"sics"`` (Mettler-Toledo MT-SICS).
        command: the query (default ``Q`` for A&D, ``SI`` for MT-SICS: immediate, with the
            stability flag).
        busy_retries: MT-SICS ``S I`` (busy) replies tolerated per reading.
        garbled_retries: garbled replies (:class:`GarbledReply`: no line of the balance's protocol, or an
            ``ET`` transmission error) asked again per reading; an error the balance reports (overload, a
            wrong mode or unit) is never asked again.
    """

    quantity = "mass_g"

    def __init__(self, url: str, style: str = "ad", command: str | None = None, busy_retries: int = 5,
                 garbled_retries: int = 2, **options) -> None:
        super().__init__(url, **options)
        if style not in ("ad", "sics"):
            raise ValueError(f"balance style must be 'ad' or 'sics', got {style!r}")
        self.style = style
        self.command = command or ("Q" if style == "ad" else "SI")
        for name, value in (("busy_retries", busy_retries), ("garbled_retries", garbled_retries)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"sensor.device.{name} must be a whole number >= 0 (the queries asked again per "
                                 f"reading), got {value!r}")
        self.busy_retries, self.garbled_retries = busy_retries, garbled_retries

    def identity(self) -> dict:
        return {**super().identity(), "style": self.style, "command": self.command}

    def read(self) -> Reading:
        link = self._link()
        parse = parse_ad if self.style == "ad" else parse_sics
        busy = garbled = 0
        while True:
            link.discard_input()
            link.write((self.command + "\r\n").encode("ascii"))
            try:
                reading = parse(link.read_line(self.timeout))
            except GarbledReply as exc:
                garbled += 1
                if garbled > self.garbled_retries:
                    raise GarbledReply(f"balance {self.url} gave {garbled} garbled replies to one query (the last: "
                                       f"{exc}): check the cable, the baud rate and style={self.style!r}") from exc
                continue
            if np.isfinite(reading.value):
                return reading
            busy += 1
            if busy > self.busy_retries:
                raise SensorError(f"balance {self.url} stayed busy for {busy} queries")


class ModbusLevelSensor(Sensor):
    """A level transducer on Modbus RTU (function 0x03).

    Args:
        url: pyserial URL.
        slave: slave address (1-247).
        address: first holding register (0-based protocol address).
        data_type: ``uint16 | int16 | uint32 | int32 | float32``.
        word_order: ``"big"`` (high word first) or ``"little"``.
        scale, offset: ``value = raw * scale + offset`` (e.g. 0.001 for a reading in um).
        unit: unit of the scaled value.
    """

    def __init__(self, url: str, slave: int = 1, address: int = 0, data_type: str = "int32",
                 word_order: str = "big", scale: float = 0.001, offset: float = 0.0, unit: str = "mm",
                 **options) -> None:
        super().__init__(url, **options)
        modbus()  # the `rig` extra, checked before any port is opened
        if data_type not in DATA_TYPES:
            raise ValueError(f"data_type must be one of {sorted(DATA_TYPES)}, got {data_type!r}")
        self.slave, self.address = int(slave), int(address)
        self.data_type, self.word_order = data_type, word_order
        self.scale, self.offset, self.unit = float(scale), float(offset), unit
        self.count = DATA_TYPES[data_type][0]

    def identity(self) -> dict:
        return {**super().identity(), "slave": self.slave, "address": self.address, "data_type": self.data_type,
                "word_order": self.word_order, "scale": self.scale, "offset": self.offset}

    def connect(self) -> None:
        """Lock and open the port; ``minimalmodbus`` talks over it (``self.link.port``)."""
        lock = PortLock(self.url)
        try:
            port = open_port(self.url, timeout=self.timeout, baudrate=self.baudrate)
            self.instrument = modbus().Instrument(port, self.slave)
        except BaseException:
            lock.release()
            raise
        self.link = LineChannel(port, lock=lock)

    def read(self) -> Reading:
        self._link()
        try:
            registers = self.instrument.read_registers(self.address, self.count, functioncode=3)
        except modbus().NoResponseError as exc:
            raise RigTimeout(f"Modbus slave {self.slave} on {self.url}: {exc}") from exc
        except modbus().ModbusException as exc:  # exception replies, bad CRC, malformed frames
            raise SensorError(f"Modbus slave {self.slave} on {self.url}: {type(exc).__name__}: {exc}") from exc
        except (serial.SerialException, OSError) as exc:
            raise RigDisconnected(f"lost the link to {self.url}: {exc}") from exc
        raw = decode_registers(registers, self.data_type, self.word_order)
        return Reading(raw * self.scale + self.offset, self.unit, True)


class AveragingSensor:
    """The mean of ``n`` readings of ``sensor``; stable when every reading is stable and finite and their
    spread (max - min) is at most ``max_spread`` (``None``: no spread check).

    Args:
        sensor: the underlying :class:`Sensor`.
        n: readings per averaged value.
        max_spread: tolerance of the spread, in the sensor's unit.
        interval_s: pause between readings (s).
    """

    def __init__(self, sensor: Sensor, n: int = 1, max_spread: float | None = None, interval_s: float = 0.0) -> None:
        n = whole_number("sensor.average.n", n, 1)  # 1.5 and true were cut to 1 reading, without a word
        if max_spread is not None and (isinstance(max_spread, bool) or not isinstance(max_spread, (int, float))
                                       or not 0 <= max_spread < np.inf):
            raise ValueError(f"sensor.average.max_spread must be a number >= 0 in the sensor's unit, or null (no "
                             f"spread check), got {max_spread!r}: below 0 no reading is ever stable")
        if isinstance(interval_s, bool) or not isinstance(interval_s, (int, float)) or not 0 <= interval_s < np.inf:
            raise ValueError(f"sensor.average.interval_s must be a number of seconds >= 0 (the pause between the "
                             f"averaged readings), got {interval_s!r}")
        self.sensor, self.n, self.max_spread, self.interval_s = sensor, int(n), max_spread, float(interval_s)

    @property
    def quantity(self) -> str:
        return self.sensor.quantity

    def identity(self) -> dict:
        return {**self.sensor.identity(), "average_n": self.n, "max_spread": self.max_spread}

    def read(self) -> Reading:
        readings = []
        for i in range(self.n):
            if i and self.interval_s:
                time.sleep(self.interval_s)
            readings.append(self.sensor.read())
        values = np.array([r.value for r in readings])
        stable = all(r.stable for r in readings) and bool(np.isfinite(values).all())  # NaN or inf: not a reading
        if stable and self.max_spread is not None and np.ptp(values) > self.max_spread:
            stable = False
        return Reading(float(values.mean()), readings[0].unit, stable)
