"""TensorBoard scalars written without TensorBoard: an ``events.out.tfevents.*`` file of
``Event`` records, each a protocol buffer in a TFRecord frame, encoded here in a few lines.

A run logs a few scalars a step.  ``torch.utils.tensorboard`` costs a run's start its import
and each scalar more of the host's time than a GPU's whole step takes to launch; here a scalar
is queued as a tuple and
encoded when the queue is written.  The file is what TensorBoard's ``SummaryWriter`` writes: a
``file_version`` event, then one event per scalar with its ``simple_value``
(``tests/test_event_file.py`` reads it back with TensorBoard's own reader).

Formats: TFRecord framing (``length``, its masked CRC-32C, the record, its masked CRC-32C) and
``tensorflow/core/util/event.proto`` / ``summary.proto`` (Event: wall_time 1, step 2,
file_version 3, summary 5; Summary.value 1; Value: tag 1, simple_value 2).
"""

from __future__ import annotations

import os
import socket
import struct
import time
from pathlib import Path


def _crc32c_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
        table.append(crc)
    return table


_TABLE = _crc32c_table()


def crc32c(data: bytes) -> int:
    """CRC-32C (Castagnoli) of ``data``, TFRecord's checksum."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc = _TABLE[(crc ^ byte) & 0xFF] ^ (crc >> 8)
    return crc ^ 0xFFFFFFFF


def _masked(crc: int) -> int:
    return (((crc >> 15) | (crc << 17)) + 0xA282EAD8) & 0xFFFFFFFF


def _varint(value: int) -> bytes:
    out = bytearray()
    while True:
        bits, value = value & 0x7F, value >> 7
        out.append(bits | (0x80 if value else 0))
        if not value:
            return bytes(out)


def _field(number: int, payload: bytes) -> bytes:
    """A length-delimited protocol-buffer field."""
    return _varint(number << 3 | 2) + _varint(len(payload)) + payload


def _event(wall_time: float, step: int, body: bytes) -> bytes:
    return b"\x09" + struct.pack("<d", wall_time) + b"\x10" + _varint(step & 0xFFFFFFFFFFFFFFFF) + body


def scalar_event(tag: str, value: float, step: int, wall_time: float) -> bytes:
    """One ``Event`` with a ``Summary`` of one ``simple_value``, encoded."""
    summary_value = _field(1, tag.encode()) + b"\x15" + struct.pack("<f", float(value))
    return _event(wall_time, step, _field(5, _field(1, summary_value)))


def framed(record: bytes) -> bytes:
    """``record`` in its TFRecord frame."""
    length = struct.pack("<Q", len(record))
    return length + struct.pack("<I", _masked(crc32c(length))) + record + struct.pack("<I", _masked(crc32c(record)))


class ScalarEvents:
    """Scalars queued by :meth:`add_scalar` and appended to ``log_dir``'s events file by
    :meth:`flush` (and :meth:`close`), named as ``SummaryWriter`` names it."""

    _count = 0

    def __init__(self, log_dir: Path | str) -> None:
        ScalarEvents._count += 1
        name = f"events.out.tfevents.{int(time.time()):010d}.{socket.gethostname()}.{os.getpid()}.{ScalarEvents._count}"
        self.path = Path(log_dir) / name
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.queued: list[tuple[str, float, int, float]] = []
        self.path.write_bytes(framed(_event(time.time(), 0, _field(3, b"brain.Event:2"))))

    def add_scalar(self, tag: str, value: float, step: int) -> None:
        self.queued.append((tag, value, step, time.time()))

    def flush(self) -> None:
        if self.queued:
            with self.path.open("ab") as f:
                f.write(b"".join(framed(scalar_event(*q)) for q in self.queued))
            self.queued = []

    def close(self) -> None:
        self.flush()
