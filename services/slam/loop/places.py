"""Place recognition over keyframes: which earlier keyframes look like a new one, with no trained vocabulary.

Words: each ORB descriptor (256 bits) is hashed ``TABLES`` times, each time by ``KEY_BITS`` of its bits
(fixed positions drawn once from a seeded generator: locality-sensitive hashing for the Hamming
distance). Two descriptors a few tens of bits apart share a key in some table with a fair probability;
unrelated ones almost never. A keyframe is the set of its words (table and key in one integer).

Index: every word of every keyframe added, sorted, with its keyframe (an inverted file in arrays,
extended as keyframes come). A query scores each indexed keyframe by the words it shares with the
query, each weighted by its inverse document frequency ``log(K / n_word)`` (K keyframes indexed, the
word in ``n_word`` of them), normalised by both keyframes' word counts (a cosine of binary tf-idf
vectors). Words seen in most keyframes (repeated texture) weigh little.

Loop candidates (``PlaceIndex.loop_candidates``, ORB-SLAM's detection): the keyframes scoring at least
the lowest score of the query's own covisible neighbours (a place must look as much like the query as
its neighbours do), the neighbours themselves left out; each candidate's score accumulated over its
covisible group, and the groups within ``GROUP_SHARE`` of the best kept.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable

import numpy as np

__all__ = ["GROUP_SHARE", "KEY_BITS", "TABLES", "PlaceIndex", "words"]

TABLES = 8
KEY_BITS = 20
SEED = 7
GROUP_SHARE = 0.75
"""A candidate group is kept when its accumulated score is at least this share of the best group's."""

_BITS = np.random.default_rng(SEED).permuted(np.tile(np.arange(256), (TABLES, 1)), axis=1)[:, :KEY_BITS]
"""(TABLES, KEY_BITS) the descriptor bits each table's key is made of (distinct within a table)."""


def words(descriptors: np.ndarray) -> np.ndarray:
    """(W,) int64 sorted distinct words of (N, 32) uint8 ORB descriptors: table ``t``'s key ``k`` is the
    word ``t << KEY_BITS | k``."""
    bits = np.unpackbits(np.asarray(descriptors, np.uint8).reshape(-1, 32), axis=1)
    keys = (bits[:, _BITS].astype(np.int64) << np.arange(KEY_BITS, dtype=np.int64)).sum(axis=2)
    return np.unique(keys + (np.arange(TABLES, dtype=np.int64) << KEY_BITS))


class PlaceIndex:
    """The words of keyframes added so far, queried by score."""

    def __init__(self) -> None:
        self._words = np.zeros(0, np.int64)
        """(M,) every indexed word, sorted; ``_owners`` (M,) the keyframe of each."""
        self._owners = np.zeros(0, np.int64)
        self._counts: dict[int, int] = {}
        """Keyframe id -> how many words it has."""

    def __contains__(self, keyframe_id: int) -> bool:
        return keyframe_id in self._counts

    def __len__(self) -> int:
        return len(self._counts)

    def add(self, keyframe_id: int, descriptors: np.ndarray) -> None:
        """Index keyframe ``keyframe_id`` by its (N, 32) descriptors (again: nothing changes)."""
        if keyframe_id in self._counts:
            return
        found = words(descriptors)
        merged = np.r_[self._words, found]
        order = np.argsort(merged, kind="stable")
        self._words = merged[order]
        self._owners = np.r_[self._owners, np.full(len(found), keyframe_id, np.int64)][order]
        self._counts[keyframe_id] = len(found)

    def scores(self, descriptors: np.ndarray) -> dict[int, float]:
        """Indexed keyframe id -> similarity in [0, 1] to a frame of (N, 32) descriptors (keyframes sharing
        no word left out)."""
        if not self._counts or len(descriptors) == 0:
            return {}
        query = words(descriptors)
        low, high = np.searchsorted(self._words, query, "left"), np.searchsorted(self._words, query, "right")
        spans = high - low
        hit = spans > 0
        low, spans = low[hit], spans[hit]
        rows = np.repeat(low - np.r_[0, np.cumsum(spans)[:-1]], spans) + np.arange(int(spans.sum()))
        idf = np.repeat(np.log(len(self._counts) / spans), spans)
        owners = self._owners[rows]
        ids, inverse = np.unique(owners, return_inverse=True)
        shared = np.bincount(inverse, idf, len(ids))
        norm = math.log(max(len(self._counts), 2))
        return {k: float(v / (norm * math.sqrt(len(query) * self._counts[k])))
                for k, v in zip(ids.tolist(), shared.tolist(), strict=True)}

    def loop_candidates(self, keyframe_id: int, descriptors: np.ndarray, neighbours: set[int],
                        group_of: Callable[[int], Iterable[int]]) -> list[int]:
        """Keyframes that may show the place keyframe ``keyframe_id`` (its (N, 32) ``descriptors``) shows,
        best first (module docstring): ``neighbours`` its covisible keyframes (left out, their lowest score
        the bar); ``group_of(candidate)`` a candidate's covisible keyframes."""
        scored = self.scores(descriptors)
        scored.pop(keyframe_id, None)
        bar_of = [scored.get(k, 0.0) for k in neighbours]
        bar = min(bar_of) if bar_of else 0.0
        above = {k: v for k, v in scored.items() if k not in neighbours and v >= bar and v > 0}
        if not above:
            return []
        accumulated = {}
        for candidate in above:
            group = set(group_of(candidate)) | {candidate}
            accumulated[candidate] = sum(above.get(k, 0.0) for k in group)
        best = max(accumulated.values())
        kept = [k for k, v in accumulated.items() if v >= GROUP_SHARE * best]
        return sorted(kept, key=lambda k: -accumulated[k])
