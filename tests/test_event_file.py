"""The TensorBoard events file the engine writes without TensorBoard reads back in TensorBoard."""

import struct

import pytest

from gaussian_atoms_method.engine.event_file import ScalarEvents, crc32c


def test_crc32c_is_castagnolis():
    """The standard check value of CRC-32C (RFC 3720, B.4): ``123456789`` -> 0xE3069283."""
    assert crc32c(b"123456789") == 0xE3069283
    assert crc32c(bytes(32)) == 0x8A9136AA


def test_scalars_read_back_in_tensorboard(tmp_path):
    """Scalars queued and flushed twice are TensorBoard's scalars: the same tags, steps and
    values (float32, the format's ``simple_value``), in order, and steps beyond 2^31."""
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = ScalarEvents(tmp_path)
    written = {"learning_rate/means": [], "Train Loss": []}
    for step in range(25):
        for tag in written:
            value = 0.1 * step + (tag == "Train Loss")
            events.add_scalar(tag, value, step)
            written[tag].append((step, struct.unpack("<f", struct.pack("<f", value))[0]))
        if step == 10:
            events.flush()
    events.add_scalar("Train Loss", 2.5, 2**33)
    written["Train Loss"].append((2**33, 2.5))
    events.close()
    (path,) = tmp_path.glob("events.out.tfevents.*")
    accumulator = EventAccumulator(str(path))
    accumulator.Reload()
    assert sorted(accumulator.Tags()["scalars"]) == sorted(written)
    for tag, expected in written.items():
        assert [(e.step, e.value) for e in accumulator.Scalars(tag)] == expected
