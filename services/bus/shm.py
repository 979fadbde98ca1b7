"""Large payloads written into Zenoh shared memory by the publisher, and read back with one copy.

What the pinned binding (eclipse-zenoh 1.10.2, ``zenoh.shm``) allows:

* Sending: a ``ZShmMut`` takes slice assignment from ``bytes`` or ``bytearray`` only (no numpy
  array, no memoryview) and exposes no buffer to write into, so pixels cannot be written into
  shared memory without a ``bytes`` of them first. ``Publisher.put`` of a ``bytes`` payload
  costs the publisher three copies of it: ``encode``'s join, the binding's ``ZBytes`` copy of the
  ``bytes``, and Zenoh's own (implicit) copy into its shared-memory pool on the way to a peer on
  the same host. Written here, it costs two: the join, and the one copy into this pool, which the
  ``ZShmMut`` then hands to Zenoh without another.
* Receiving: neither ``ZBytes`` nor ``ZShm`` has the buffer protocol, so a numpy view of a
  payload needs one copy into a ``bytes``. ``bytes(zshm)`` makes that copy once, where
  ``ZBytes.to_bytes`` zero-fills its ``bytes`` first and then copies: ``received_bytes`` takes
  the shared-memory buffer when there is one.

Zenoh delivers a shared-memory payload to a peer that cannot map it (another host, or a session
with ``transport/shared_memory/enabled: false``) as ordinary bytes, copying it itself.
"""

from __future__ import annotations

import logging

import zenoh
import zenoh.shm

log = logging.getLogger(__name__)

THRESHOLD = 3072
"""Payloads shorter than this (bytes; poses, detections) go as plain ``bytes``: allocating from the
pool costs more than copying them. Zenoh's own threshold for its implicit shared memory is the same."""

POOL_PAYLOADS = 8
"""How many payloads of the largest size seen so far a pool holds: twice the frames a lossless run's
credits let be in flight, for the bursts a flood makes (with 4, a zero-loss flood of 640x480 frames
fell back to plain bytes more often and ran slower than without the pool; docs/benchmarks.md).
Zenoh locks a pool in memory as it makes it (``mlock``), so a pool costs its full size in RAM and in
``/dev/shm`` at once (8 x 2.8 MB for 1280x720 bgr8), and a process without ``CAP_IPC_LOCK`` gets
pools only up to its ``RLIMIT_MEMLOCK`` in all (often 8 MiB): beyond it, no pool. Chunks that
subscribers have released are collected before each allocation, so the one just released is
written again while it is still in the caches."""

CHUNK_SLACK = 4096
"""Bytes of pool kept per payload besides its own: a pool of exactly k payloads' bytes holds only k - 1 of them."""

_ALLOC_POLICY = zenoh.shm.Defragment(zenoh.shm.GarbageCollect())
"""When no free chunk fits: merge free neighbours, collect released chunks, try again; never wait
(Zenoh's ``BlockOn`` polls every millisecond)."""


class ShmPayloads:
    """One publisher's shared-memory pool, made on the first payload of ``threshold`` bytes or more
    and remade larger when a payload would not fit ``POOL_PAYLOADS`` times.

    ``payload(data)`` is ``data`` copied into a chunk of the pool (a ``ZShmMut`` to put), or
    ``data`` itself when it is short, when the pool has no free chunk (every chunk still held by
    subscribers) or when no pool can be made (no POSIX shared memory here; then none is tried
    again): the message then goes the ordinary way and still arrives.
    """

    def __init__(self, threshold: int = THRESHOLD, pool_payloads: int = POOL_PAYLOADS):
        self.threshold = threshold
        self.pool_payloads = pool_payloads
        self.pool_bytes = 0
        self.fallbacks = 0
        self.unavailable = False
        self._provider: zenoh.shm.ShmProvider | None = None

    def payload(self, data: bytes) -> zenoh.shm.ZShmMut | bytes:
        size = len(data)
        if size < self.threshold or self.unavailable:
            return data
        wanted = (size + CHUNK_SLACK) * self.pool_payloads
        if wanted > self.pool_bytes:
            try:
                self._provider = zenoh.shm.ShmProvider.default_backend(wanted)
            except zenoh.ZError as error:
                log.warning("no shared-memory pool of %d bytes (%s): large payloads go as plain bytes", wanted, error)
                self.unavailable = True
                return data
            self.pool_bytes = wanted
        assert self._provider is not None
        self._provider.garbage_collect()
        try:
            chunk = self._provider.alloc(size, _ALLOC_POLICY)
        except zenoh.ZError:
            self.fallbacks += 1
            return data
        chunk[:] = data
        return chunk


def received_bytes(payload: zenoh.ZBytes) -> bytes:
    """``payload``'s bytes, copied once out of shared memory when it arrived there."""
    chunk = payload.as_shm()
    return payload.to_bytes() if chunk is None else bytes(chunk)
