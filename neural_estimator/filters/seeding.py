"""numpy's keyed generators, ``SFC64(SeedSequence(seed, spawn_key=key))``, without their set-up cost.

The classical filters draw from one generator per (step, phase, block) (:mod:`.scheduler`), so that
the numbers never depend on threads or blocking. Building it the plain way,
``np.random.Generator(np.random.SFC64(np.random.SeedSequence(seed, spawn_key=key)))``, costs about
40 us (the SeedSequence's hashing in Python-level Cython loops, then ``generate_state``): two of them
a step were a fifth of the EnKF's step at batch 1. :class:`KeyedSFC64` produces the very same
generator state with one compiled call (under a microsecond) and writes it into a reused SFC64
bit generator (``state`` setter, about 1 us).

The state is numpy's by construction, word for word:

- SeedSequence (O'Neill's ``seed_seq`` alternative, numpy/random/bit_generator.pyx): the entropy is
  the seed's 32-bit words (lowest first; 0 is one word), zero-padded to the pool size 4 when a spawn
  key is given, then the key's words. The first 4 words are hashed into the pool and cross-mixed;
  every further word is hashed and mixed into each pool word. The seed part is the same for every
  key, so it is done once (:class:`KeyedSFC64` caches the pool and the running hash constant) and
  only the key's words are mixed per call. ``generate_state(3, uint64)`` then hashes the pool
  cyclically into 6 32-bit words, paired little-endian into 3 64-bit words.
- SFC64 (numpy/random/src/sfc64): a, b, c = those words, counter w = 1, then 12 rounds discarded.

The tests compare the state and the draws with numpy's own construction for many keys and seeds.
"""

from __future__ import annotations

import numba as nb
import numpy as np

_M32 = 0xFFFFFFFF
_INIT_A, _MULT_A = 0x43B0D7E5, 0x931E8875
_INIT_B, _MULT_B = 0x8B51F9DD, 0x58F38DED
_MIX_L, _MIX_R = 0xCA01F9DD, 0x4973F715
_POOL = 4


def _words(n: int) -> list[int]:
    """A non-negative integer as numpy coerces it: 32-bit words, lowest first; 0 is [0]."""
    if n < 0:
        raise ValueError(f"seed and key must be non-negative integers, got {n}")
    out = [n & _M32] if n == 0 else []
    while n > 0:
        out.append(n & _M32)
        n >>= 32
    return out


def _hashmix(value: int, hc: list[int]) -> int:
    value = (value ^ hc[0]) & _M32
    hc[0] = (hc[0] * _MULT_A) & _M32
    value = (value * hc[0]) & _M32
    return value ^ (value >> 16)


def _mix(x: int, y: int) -> int:
    r = (_MIX_L * x - _MIX_R * y) & _M32
    return r ^ (r >> 16)


def seed_pool(seed: int) -> tuple[np.ndarray, int]:
    """The SeedSequence pool (4 uint32 words) and running hash constant after mixing in ``seed``'s
    words (padded to the pool size, as numpy does when a spawn key follows)."""
    run = _words(int(seed))
    run += [0] * (_POOL - len(run))
    hc = [_INIT_A]
    pool = [_hashmix(run[i], hc) for i in range(_POOL)]
    for src in range(_POOL):
        for dst in range(_POOL):
            if src != dst:
                pool[dst] = _mix(pool[dst], _hashmix(pool[src], hc))
    for word in run[_POOL:]:
        for dst in range(_POOL):
            pool[dst] = _mix(pool[dst], _hashmix(word, hc))
    return np.array(pool, dtype=np.uint64), hc[0]


@nb.njit(cache=True)
def _mix_word(pool, hc, word):
    """Mix one 32-bit entropy word into each pool word (SeedSequence.mix_entropy's last loop)."""
    m = np.uint64(0xFFFFFFFF)
    for dst in range(4):
        v = (word ^ hc) & m
        hc = (hc * np.uint64(0x931E8875)) & m
        v = (v * hc) & m
        v ^= v >> np.uint64(16)
        r = (np.uint64(0xCA01F9DD) * pool[dst] - np.uint64(0x4973F715) * v) & m
        pool[dst] = r ^ (r >> np.uint64(16))
    return hc


@nb.njit(cache=True)
def sfc64_state(pool0, hc0, k0, k1, k2):
    """SFC64's state words (a, b, c, counter), 4 uint64, for the key (k0, k1, k2) (integers
    0 <= k < 2^63) after the seed's ``pool0`` / ``hc0`` (:func:`seed_pool`)."""
    m = np.uint64(0xFFFFFFFF)
    pool = pool0.copy()
    hc = np.uint64(hc0)
    for value in (k0, k1, k2):
        v = np.uint64(value)
        if v == 0:
            hc = _mix_word(pool, hc, np.uint64(0))
        while v > 0:
            hc = _mix_word(pool, hc, v & m)
            v >>= np.uint64(32)
    # generate_state(3, uint64): 6 words hashed from the pool cyclically, paired little-endian
    h = np.uint64(0x8B51F9DD)
    words = np.empty(6, dtype=np.uint64)
    for i in range(6):
        d = pool[i % 4] ^ h
        h = (h * np.uint64(0x58F38DED)) & m
        d = (d * h) & m
        words[i] = d ^ (d >> np.uint64(16))
    a = words[0] | (words[1] << np.uint64(32))
    b = words[2] | (words[3] << np.uint64(32))
    c = words[4] | (words[5] << np.uint64(32))
    w = np.uint64(1)
    for _ in range(12):  # sfc64_set_seed: twelve rounds discarded
        tmp = a + b + w
        w += np.uint64(1)
        a = b ^ (b >> np.uint64(11))
        b = c + (c << np.uint64(3))
        c = ((c << np.uint64(24)) | (c >> np.uint64(40))) + tmp
    out = np.empty(4, dtype=np.uint64)
    out[0], out[1], out[2], out[3] = a, b, c, w
    return out


class KeyedSFC64:
    """``np.random.Generator(np.random.SFC64(np.random.SeedSequence(seed, spawn_key=key)))``, fast.

    ``pool`` / ``hc``: the seed's part of the SeedSequence (:func:`seed_pool`), for compiled callers
    of :func:`sfc64_state`. :meth:`generator` returns a generator in exactly that state. Generators are reused per
    ``slot``: the one returned for a slot is valid until the next call for the same slot (each
    block of streams and phase has its own slot, and a block runs on one thread at a time).
    """

    def __init__(self, seed: int) -> None:
        self.seed = int(seed)
        self.pool, self.hc = seed_pool(self.seed)
        self._gens: dict = {}

    def state(self, key: tuple[int, int, int]) -> np.ndarray:
        """SFC64's state words (a, b, c, counter) for ``key``: three integers 0 <= k < 2^63."""
        if len(key) != 3 or not all(0 <= int(v) < 2**63 for v in key):
            raise ValueError(f"key must be three integers in [0, 2^63), got {key!r}")
        return sfc64_state(self.pool, self.hc, int(key[0]), int(key[1]), int(key[2]))

    def generator(self, key: tuple[int, int, int], slot) -> np.random.Generator:
        """The generator of ``key`` (three integers 0 <= k < 2^63, unchecked: the caller's step,
        phase and block), on ``slot``'s object."""
        gen = self._gens.get(slot)
        if gen is None:
            gen = self._gens[slot] = np.random.Generator(np.random.SFC64(0))
        gen.bit_generator.state = {
            "bit_generator": "SFC64",
            "state": {"state": sfc64_state(self.pool, self.hc, *key)},
            "has_uint32": 0,
            "uinteger": 0,
        }
        return gen
