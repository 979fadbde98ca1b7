"""A publisher's shared-memory payloads: short ones stay bytes, large ones land in the pool intact,
an exhausted pool falls back to bytes, and reading back gives what ``ZBytes.to_bytes`` gives."""

from __future__ import annotations

import numpy as np
import pytest
import zenoh

from services.bus.shm import CHUNK_SLACK, THRESHOLD, ShmPayloads, received_bytes


def _data(size: int, seed: int = 0) -> bytes:
    return np.random.default_rng(seed).integers(0, 256, size, dtype=np.uint8).tobytes()


def test_a_payload_below_the_threshold_is_returned_as_it_is_and_makes_no_pool():
    payloads = ShmPayloads()
    data = _data(THRESHOLD - 1)
    assert payloads.payload(data) is data
    assert payloads.pool_bytes == 0


@pytest.mark.parametrize("size", [THRESHOLD, 307_456])
def test_a_large_payload_lands_in_shared_memory_intact(size):
    data = _data(size)
    chunk = ShmPayloads().payload(data)
    assert isinstance(chunk, zenoh.shm.ZShmMut)
    sent = zenoh.ZBytes(chunk)
    assert sent.as_shm() is not None
    assert received_bytes(sent) == data


def test_an_exhausted_pool_falls_back_to_bytes_and_recovers_once_chunks_are_released():
    payloads = ShmPayloads(threshold=1024, pool_payloads=2)
    data = _data(100_000)
    held = [zenoh.ZBytes(payloads.payload(data)) for _ in range(2)]  # subscribers still reading both
    assert all(z.as_shm() is not None for z in held)
    assert payloads.payload(data) is data
    assert payloads.fallbacks == 1
    held.clear()
    again = payloads.payload(data)
    assert isinstance(again, zenoh.shm.ZShmMut)
    assert payloads.fallbacks == 1


def test_a_larger_payload_grows_the_pool_and_chunks_of_the_old_one_stay_readable():
    payloads = ShmPayloads(threshold=1024, pool_payloads=2)
    small, large = _data(10_000, 1), _data(50_000, 2)
    old = zenoh.ZBytes(payloads.payload(small))
    assert payloads.pool_bytes == 2 * (10_000 + CHUNK_SLACK)
    new = zenoh.ZBytes(payloads.payload(large))
    assert payloads.pool_bytes == 2 * (50_000 + CHUNK_SLACK)
    assert (received_bytes(old), received_bytes(new)) == (small, large)


@pytest.mark.parametrize("size", [0, 1, 5_000, 921_600])
def test_received_bytes_equal_to_bytes_for_plain_and_shared_memory_payloads(size):
    data = _data(size, 3)
    plain = zenoh.ZBytes(data)
    assert plain.as_shm() is None
    assert received_bytes(plain) == plain.to_bytes() == data
    if size:
        shared = zenoh.ZBytes(ShmPayloads(threshold=1).payload(data))
        assert shared.as_shm() is not None
        assert received_bytes(shared) == shared.to_bytes() == data


def test_without_shared_memory_large_payloads_stay_bytes_and_no_pool_is_tried_again(monkeypatch):
    tries = []

    class Refusing:
        @staticmethod
        def default_backend(size: int):
            tries.append(size)
            raise zenoh.ZError("no /dev/shm")

    monkeypatch.setattr(zenoh.shm, "ShmProvider", Refusing)
    payloads = ShmPayloads()
    data = _data(50_000)
    assert [payloads.payload(data) is data for _ in range(3)] == [True] * 3
    assert (len(tries), payloads.unavailable, payloads.pool_bytes) == (1, True, 0)
