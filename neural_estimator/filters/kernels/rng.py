"""Compiled (numba) random numbers of the filters' kernels: two families of standard normals.

The PF's keyed generators. The numpy particle filter spends its time, per particle and step, on the
process-noise draws (numpy's fastest normal generator, SFC64, costs 8.7 ns a number), on the
transition f and on the likelihood; the PF's kernels fuse them per particle (:func:`add_process_noise`,
and the scenarios' ``*_predict`` in their own modules, which call :func:`_seed_state` and
:func:`_add_noise`). Each stream draws from its own generator, keyed by (seed, step k, phase, stream
index b): the key is mixed by SplitMix64 (Steele, Lea & Flood 2014) into the 256-bit state of a
xoshiro256** generator (Blackman & Vigna 2018). Standard normals come from the 256-layer ziggurat
of Marsaglia & Tsang (2000), in the 64-bit form numpy uses (one 64-bit word gives the layer, the
sign and a 52-bit abscissa; about 99 % of draws cost one word, one multiply and one compare).
The draws of a stream therefore depend only on (seed, k, phase, b): results are identical for any
thread count, block size or batch size. They are not numpy's numbers: the compiled PF equals the
numpy PF in distribution, and equals it exactly given the same draws (:func:`stream_normals`
returns a stream's draws, the tests feed them to the numpy path).

numpy's own SFC64 normals (the compiled EnKF, :mod:`.enkf`): the block's generator state is derived
from the key (seed, step, phase, block) as ``SFC64(SeedSequence(seed, spawn_key=key))`` does
(:mod:`neural_estimator.filters.seeding`), and the standard normals follow numpy's
``Generator.standard_normal``: SFC64's 64-bit words through numpy's 256-layer ziggurat, with numpy's
own tables (as numba's port of numpy's generator carries them); :func:`standard_normals` returns
them (the tests hold them equal to numpy's).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numba.np.random._constants import fi_double, ki_double, wi_double, ziggurat_nor_inv_r, ziggurat_nor_r

from neural_estimator.filters.seeding import sfc64_state

# ---- keyed generators ---------------------------------------------------------------------------
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31 = np.uint64(30), np.uint64(27), np.uint64(31)


@nb.njit(inline="always")
def _splitmix(x):
    """One SplitMix64 output for state x (state advanced by the caller): a bijective 64-bit mix."""
    z = x + _GOLDEN
    z = (z ^ (z >> _S30)) * _MIX1
    z = (z ^ (z >> _S27)) * _MIX2
    return z ^ (z >> _S31)


@nb.njit(inline="always")
def _rotl(x, k):
    return (x << np.uint64(k)) | (x >> np.uint64(64 - k))


@nb.njit(inline="always")
def _seed_state(state, seed, k, phase, stream):
    """xoshiro256** state from the key (seed, k, phase, stream): each key word is folded in by a
    SplitMix64 round, then four more rounds fill the state (never all zero: SplitMix is a bijection
    of distinct inputs, and four consecutive outputs cannot all vanish)."""
    h = np.uint64(seed)
    h = _splitmix(h ^ np.uint64(k))
    h = _splitmix(h ^ np.uint64(phase) ^ np.uint64(0x5851F42D4C957F2D))
    h = _splitmix(h ^ np.uint64(stream))
    for i in range(4):
        h = h + _GOLDEN
        state[i] = _splitmix(h)


@nb.njit(inline="always")
def _next_u64(s):
    """xoshiro256**: the next 64-bit word of state s (4 uint64), s advanced in place.

    The state is read into locals and written back once, so the compiler keeps it in registers
    across the inlined calls of a loop instead of reloading it around every store to an output.
    """
    s0, s1, s2, s3 = s[0], s[1], s[2], s[3]
    result = _rotl(s1 * np.uint64(5), 7) * np.uint64(9)
    t = s1 << np.uint64(17)
    s2 ^= s0
    s3 ^= s1
    s1 ^= s2
    s0 ^= s3
    s2 ^= t
    s3 = _rotl(s3, 45)
    s[0], s[1], s[2], s[3] = s0, s1, s2, s3
    return result


@nb.njit(inline="always")
def _next_double(s):
    """Uniform on [0, 1) with 53 random bits."""
    return float(np.int64(_next_u64(s) >> np.uint64(11))) * (1.0 / 9007199254740992.0)


def _ziggurat_tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Marsaglia & Tsang's 256-layer tables for exp(-x^2/2) with 52-bit abscissae.

    r = 3.6541528853610088 is the base strip's right edge and v = 4.92867323399e-3 each layer's
    area; ki[i] (integer thresholds), wi[i] (abscissa scale) and fi[i] = f(x_i) follow the paper's
    recursion x_i = sqrt(-2 log(v / x_{i+1} + f(x_{i+1}))).
    """
    m1 = 2.0**52
    dn = tn = 3.6541528853610088
    vn = 4.92867323399e-3
    ki = np.zeros(256, dtype=np.int64)
    wi = np.zeros(256)
    fi = np.zeros(256)
    q = vn / math.exp(-0.5 * dn * dn)
    ki[0] = int((dn / q) * m1)
    ki[1] = 0
    wi[0] = q / m1
    wi[255] = dn / m1
    fi[0] = 1.0
    fi[255] = math.exp(-0.5 * dn * dn)
    for i in range(254, 0, -1):
        dn = math.sqrt(-2.0 * math.log(vn / dn + math.exp(-0.5 * dn * dn)))
        ki[i + 1] = int((dn / tn) * m1)
        tn = dn
        fi[i] = math.exp(-0.5 * dn * dn)
        wi[i] = dn / m1
    return ki, wi, fi


_KI, _WI, _FI = _ziggurat_tables()
_ZIG_R = 3.6541528853610088
_MASK52 = np.uint64(0x000FFFFFFFFFFFFF)


@nb.njit(inline="always")
def _zig_slow(s, idx, rabs, x):
    """The ziggurat's rare branches for a word that missed the rectangle test (about 1 % of draws):
    the tail beyond r for layer 0, else the wedge test; NaN asks the caller for a new word."""
    if idx == 0:  # the tail beyond r
        while True:
            xx = -math.log1p(-_next_double(s)) / _ZIG_R
            yy = -math.log1p(-_next_double(s))
            if yy + yy > xx * xx:
                return -(_ZIG_R + xx) if (rabs >> 8) & 1 else _ZIG_R + xx
    if (_FI[idx - 1] - _FI[idx]) * _next_double(s) + _FI[idx] < math.exp(-0.5 * x * x):
        return x
    return math.nan


@nb.njit(inline="always")
def _fill_normals(s, z, count):
    """z[:count] <- standard normals from generator state s (ziggurat; tail by Marsaglia's 1964
    method), s advanced in place.

    The fast path (one 64-bit word: 8 bits of layer, a sign bit, a 52-bit abscissa, one compare)
    keeps the xoshiro256** state in local variables over all ``count`` draws; it goes through the
    array ``s`` only around the rare branches. With the state in memory, every draw's four loads
    and stores sat on the generator's dependency chain (measured 9 ns a normal; now about half).
    The numbers are those of drawing one at a time, in the same order.
    """
    s0, s1, s2, s3 = s[0], s[1], s[2], s[3]
    for j in range(count):
        while True:
            r = _rotl(s1 * np.uint64(5), 7) * np.uint64(9)
            t = s1 << np.uint64(17)
            s2 ^= s0
            s3 ^= s1
            s1 ^= s2
            s0 ^= s3
            s2 ^= t
            s3 = _rotl(s3, 45)
            idx = np.int64(r & np.uint64(0xFF))
            r = r >> np.uint64(8)
            negative = (r & np.uint64(1)) != np.uint64(0)
            rabs = np.int64((r >> np.uint64(1)) & _MASK52)  # 52 bits: int64 converts to float fast
            x = float(rabs) * _WI[idx]
            if negative:
                x = -x
            if rabs < _KI[idx]:
                z[j] = x
                break
            s[0], s[1], s[2], s[3] = s0, s1, s2, s3
            x = _zig_slow(s, idx, rabs, x)
            s0, s1, s2, s3 = s[0], s[1], s[2], s[3]
            if x == x:
                z[j] = x
                break
    s[0], s[1], s[2], s[3] = s0, s1, s2, s3


@nb.njit(nogil=True, cache=True)
def stream_normals(seed: int, k: int, phase: int, stream: int, count: int) -> np.ndarray:
    """The first ``count`` standard normals of one stream's generator (for tests and references)."""
    s = np.empty(4, dtype=np.uint64)
    _seed_state(s, seed, k, phase, stream)
    out = np.empty(count)
    _fill_normals(s, out, count)
    return out


# ---- process noise --------------------------------------------------------------------------------
@nb.njit(inline="always")
def _add_noise(x, s, L, sd, z):
    """x += L z, z standard normal (n draws per particle, in component order); sd (diagonal
    sqrt(Q)) replaces L when it is given (sd.size > 0), as ``numerics.gaussian`` does. L is any
    square root of Q (the scenarios' psd_sqrt is symmetric, not triangular)."""
    n = x.shape[0]
    _fill_normals(s, z, n)
    if sd.size:
        for j in range(n):
            x[j] += z[j] * sd[j]
    else:
        for j in range(n):
            acc = 0.0
            for i in range(n):
                acc += L[j, i] * z[i]
            x[j] += acc


@nb.njit(nogil=True, cache=True)
def add_process_noise(X, L, sd, seed, k, phase, first_stream):
    """X (b, N, n) += w, w ~ N(0, L L^T) per particle, drawn from each stream's keyed generator."""
    b, N, n = X.shape
    s = np.empty(4, dtype=np.uint64)
    z = np.empty(n)
    for r in range(b):
        _seed_state(s, seed, k, phase, first_stream + r)
        for i in range(N):
            _add_noise(X[r, i], s, L, sd, z)


# ---- numpy's SFC64 and standard normal (the compiled EnKF) ----------------------------------------
_NP_KI = np.ascontiguousarray(ki_double, dtype=np.uint64)
_NP_WI = np.ascontiguousarray(wi_double, dtype=np.float64)
_NP_FI = np.ascontiguousarray(fi_double, dtype=np.float64)
_NOR_R = float(ziggurat_nor_r)
_NOR_INV_R = float(ziggurat_nor_inv_r)


@nb.njit(inline="always")
def _sfc64_next(s):
    """SFC64's next 64-bit word; state s = (a, b, c, counter) advanced in place."""
    a, b, c, w = s[0], s[1], s[2], s[3]
    tmp = a + b + w
    s[3] = w + np.uint64(1)
    s[0] = b ^ (b >> np.uint64(11))
    s[1] = c + (c << np.uint64(3))
    s[2] = ((c << np.uint64(24)) | (c >> np.uint64(40))) + tmp
    return tmp


@nb.njit(inline="always")
def _sfc64_double(s):
    return float(_sfc64_next(s) >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@nb.njit
def _sfc64_normal_slow(s, idx, rabs, x):
    """The ziggurat's rare branches (numpy's random_standard_normal): the tail beyond r for layer 0,
    else the wedge test; NaN asks for a new word."""
    if idx == 0:
        while True:
            xx = -_NOR_INV_R * math.log1p(-_sfc64_double(s))
            yy = -math.log1p(-_sfc64_double(s))
            if yy + yy > xx * xx:
                return -(_NOR_R + xx) if (rabs >> np.uint64(8)) & np.uint64(1) else _NOR_R + xx
    if (_NP_FI[idx - 1] - _NP_FI[idx]) * _sfc64_double(s) + _NP_FI[idx] < math.exp(-0.5 * x * x):
        return x
    return math.nan


@nb.njit(inline="always")
def _sfc64_fill_normals(s, z):
    """z (1-D) <- the next len(z) standard normals of state s, as numpy's random_standard_normal (a
    64-bit word: 8 bits layer, 1 sign, 52 abscissa; the rare branches in :func:`_sfc64_normal_slow`), with SFC64's
    state held in locals across the common branch (stored back only around the rare one), so the
    compiler keeps it in registers: about twice as fast as a call per number."""
    a, b, c, w = s[0], s[1], s[2], s[3]
    i = 0
    count = z.shape[0]
    while i < count:
        tmp = a + b + w
        w += np.uint64(1)
        a = b ^ (b >> np.uint64(11))
        b = c + (c << np.uint64(3))
        c = ((c << np.uint64(24)) | (c >> np.uint64(40))) + tmp
        idx = np.int64(tmp & np.uint64(0xFF))
        r = tmp >> np.uint64(8)
        rabs = (r >> np.uint64(1)) & np.uint64(0x000FFFFFFFFFFFFF)
        x = float(rabs) * _NP_WI[idx]
        if r & np.uint64(1):
            x = -x
        if rabs < _NP_KI[idx]:
            z[i] = x
            i += 1
            continue
        s[0], s[1], s[2], s[3] = a, b, c, w
        x = _sfc64_normal_slow(s, idx, rabs, x)
        a, b, c, w = s[0], s[1], s[2], s[3]
        if not math.isnan(x):
            z[i] = x
            i += 1
    s[0], s[1], s[2], s[3] = a, b, c, w


@nb.njit(cache=True)
def standard_normals(pool, hc, k0, k1, k2, count):
    """``count`` draws of ``Generator(SFC64(SeedSequence(seed, spawn_key=(k0, k1, k2)))).standard_normal``
    (for the tests)."""
    s = sfc64_state(pool, hc, k0, k1, k2)
    out = np.empty(count)
    _sfc64_fill_normals(s, out)
    return out
