"""Compiled (numba) kernels of the particle filter's predict and weight steps.

The numpy particle filter spends its time, per particle and step, on the process-noise draws
(numpy's fastest normal generator, SFC64, costs 8.7 ns a number), on the transition f and on the
likelihood. These kernels fuse them per particle, in one pass over each stream's particles, and
release the GIL so the filter's worker threads run them side by side.

Random numbers. Each stream draws from its own generator, keyed by (seed, step k, phase, stream
index b): the key is mixed by SplitMix64 (Steele, Lea & Flood 2014) into the 256-bit state of a
xoshiro256** generator (Blackman & Vigna 2018). Standard normals come from the 256-layer ziggurat
of Marsaglia & Tsang (2000), in the 64-bit form numpy uses (one 64-bit word gives the layer, the
sign and a 52-bit abscissa; about 99 % of draws cost one word, one multiply and one compare).
The draws of a stream therefore depend only on (seed, k, phase, b): results are identical for any
thread count, block size or batch size. They are not numpy's numbers: the compiled PF equals the
numpy PF in distribution, and equals it exactly given the same draws (:func:`stream_normals`
returns a stream's draws, the tests feed them to the numpy path).

Lorenz 96's transition is here (the same RK4, in the same order of operations as ``Lorenz96.f``,
bit-equal, tested); the other scenarios' kernels are in :mod:`.compiled_models`. Scenarios without
one keep their numpy ``f``; the compiled noise and likelihood kernels still apply to all.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

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


# ---- Lorenz 96 ------------------------------------------------------------------------------------
@nb.njit(inline="always")
def _l96_field(x, out, forcing):
    """dX_j/dt = (X_{j+1} - X_{j-2}) X_{j-1} - X_j + F on the ring, in Lorenz96._field's order
    (the three wrapped ends apart, so the main loop has no index arithmetic modulo J)."""
    n = x.shape[0]
    out[0] = (x[1] - x[n - 2]) * x[n - 1] - x[0] + forcing
    out[1] = (x[2] - x[n - 1]) * x[0] - x[1] + forcing
    for j in range(2, n - 1):
        out[j] = (x[j + 1] - x[j - 2]) * x[j - 1] - x[j] + forcing
    out[n - 1] = (x[0] - x[n - 3]) * x[n - 2] - x[n - 1] + forcing


@nb.njit(inline="always")
def _l96_rk4(x, forcing, h, substeps, K, A, M):
    """``substeps`` RK4 steps of length h on x in place, in rk4()'s order of operations."""
    n = x.shape[0]
    half = 0.5 * h
    sixth = h / 6.0
    for _ in range(substeps):
        _l96_field(x, K, forcing)  # k1
        for j in range(n):
            A[j] = K[j]
            M[j] = x[j] + K[j] * half
        _l96_field(M, K, forcing)  # k2
        for j in range(n):
            A[j] += K[j] * 2.0
            M[j] = x[j] + K[j] * half
        _l96_field(M, K, forcing)  # k3
        for j in range(n):
            A[j] += K[j] * 2.0
            M[j] = x[j] + K[j] * h
        _l96_field(M, K, forcing)  # k4
        for j in range(n):
            A[j] += K[j]
            A[j] *= sixth
            x[j] += A[j]


@nb.njit(nogil=True, cache=True)
def lorenz96_transition(X, forcing, h, substeps):
    """X (..., N, J) <- f(X): Lorenz 96 RK4 in place (no noise); for the tests and the reference."""
    flat = X.reshape(-1, X.shape[-1])
    n = flat.shape[1]
    K, A, M = np.empty(n), np.empty(n), np.empty(n)
    for i in range(flat.shape[0]):
        _l96_rk4(flat[i], forcing, h, substeps, K, A, M)


@nb.njit(inline="always")
def _l96_field_rows(x, out, forcing, m):
    """:func:`_l96_field` on the first m columns of (J, P) rows: the same operations per state,
    with the states innermost so the loops vectorise."""
    n = x.shape[0]
    for j in range(n):
        jp, jm1, jm2 = (j + 1) % n, (j - 1) % n, (j - 2) % n
        for i in range(m):
            out[j, i] = (x[jp, i] - x[jm2, i]) * x[jm1, i] - x[j, i] + forcing


@nb.njit(inline="always")
def _l96_rk4_rows(X, forcing, h, substeps, x, K, A, M):
    """:func:`_l96_rk4` on the m states X (m, J) (m <= P) in place, through (J, P) scratch rows."""
    m, n = X.shape
    half = 0.5 * h
    sixth = h / 6.0
    for i in range(m):
        for j in range(n):
            x[j, i] = X[i, j]
    for _ in range(substeps):
        _l96_field_rows(x, K, forcing, m)  # k1
        for j in range(n):
            for i in range(m):
                A[j, i] = K[j, i]
                M[j, i] = x[j, i] + K[j, i] * half
        _l96_field_rows(M, K, forcing, m)  # k2
        for j in range(n):
            for i in range(m):
                A[j, i] += K[j, i] * 2.0
                M[j, i] = x[j, i] + K[j, i] * half
        _l96_field_rows(M, K, forcing, m)  # k3
        for j in range(n):
            for i in range(m):
                A[j, i] += K[j, i] * 2.0
                M[j, i] = x[j, i] + K[j, i] * h
        _l96_field_rows(M, K, forcing, m)  # k4
        for j in range(n):
            for i in range(m):
                A[j, i] += K[j, i]
                A[j, i] *= sixth
                x[j, i] += A[j, i]
    for i in range(m):
        for j in range(n):
            X[i, j] = x[j, i]


@nb.njit(nogil=True, cache=True)
def lorenz96_predict(X, forcing, h, substeps, L, sd, seed, k, phase, first_stream):
    """X (b, N, J) <- f(X) + w per particle: RK4 over each stream's particles as (J, N) rows
    (vectorised across particles), then the noise particle by particle."""
    b, N, n = X.shape
    s = np.empty(4, dtype=np.uint64)
    z = np.empty(n)
    x, K, A, M = np.empty((n, N)), np.empty((n, N)), np.empty((n, N)), np.empty((n, N))
    for r in range(b):
        _l96_rk4_rows(X[r], forcing, h, substeps, x, K, A, M)
        _seed_state(s, seed, k, phase, first_stream + r)
        for i in range(N):
            _add_noise(X[r, i], s, L, sd, z)


# ---- likelihood of a linear observation with diagonal R --------------------------------------------
@nb.njit(nogil=True, cache=True)
def linear_log_likelihood(X, H, identity, y, inv_sd, logw):
    """logw (b, N) += -|(y - H x_i) / sd|^2 / 2 for every particle x_i of X (b, N, n).

    ``identity``: H is the identity (Lorenz 96), the product is skipped.
    """
    b, N, n = X.shape
    m = y.shape[1]
    for r in range(b):
        yr = y[r]
        for i in range(N):
            x = X[r, i]
            acc = 0.0
            for j in range(m):
                if identity:
                    hx = x[j]
                else:
                    hx = 0.0
                    for c in range(n):
                        hx += H[j, c] * x[c]
                e = (yr[j] - hx) * inv_sd[j]
                acc += e * e
            logw[r, i] += -0.5 * acc


# ---- weights ---------------------------------------------------------------------------------------
@nb.njit(nogil=True, cache=True)
def normalize_log_weights_rows(logw, w, floor):
    """In place, per row of logw (b, N): ``numerics.normalize_log_weights`` in one kernel.

    m = max_i l_i, d_i = l_i - m, w_i = exp(d_i) / s with s = sum_j exp(d_j) (relative weights with
    d_i <= floor are exactly 0: no subnormals), l_i <- d_i - log s. A row whose maximum is not
    finite (all -inf, or a NaN) becomes NaN in both (the caller flags the stream as diverged).
    """
    b, N = logw.shape
    for r in range(b):
        m = -np.inf
        nan = False
        for i in range(N):
            v = logw[r, i]
            if v != v:
                nan = True
            elif v > m:
                m = v
        if nan or not (m > -np.inf and m < np.inf):
            for i in range(N):
                logw[r, i] = np.nan
                w[r, i] = np.nan
            continue
        s = 0.0
        for i in range(N):
            d = logw[r, i] - m
            e = math.exp(d) if d > floor else 0.0
            logw[r, i] = d
            w[r, i] = e
            s += e
        log_s = math.log(s)
        for i in range(N):
            w[r, i] /= s
            logw[r, i] -= log_s


# ---- systematic resampling ------------------------------------------------------------------------
@nb.njit(nogil=True, cache=True)
def systematic_resample_rows(X, w, offsets, need):
    """X[r] <- X[r, idx_r] for the rows r with need[r], in place: systematic resampling with
    positions p_i = (offsets[r] + i) / N and idx_r[i] = the first j with p_i < c_j, c the cumulative
    weights with c_{N-1} set to 1 (``numerics.systematic_resample`` on one row, walked in O(N))."""
    b, N, n = X.shape
    tmp = np.empty((N, n))
    c = np.empty(N)
    for r in range(b):
        if not need[r]:
            continue
        acc = 0.0
        for j in range(N):
            acc += w[r, j]
            c[j] = acc
        c[N - 1] = 1.0
        j = 0
        for i in range(N):
            p = (offsets[r] + i) / N
            while j < N - 1 and p >= c[j]:
                j += 1
            for m in range(n):
                tmp[i, m] = X[r, j, m]
        for i in range(N):
            for m in range(n):
                X[r, i, m] = tmp[i, m]
