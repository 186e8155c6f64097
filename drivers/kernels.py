"""The drivers' compiled kernels: the output gate's check (:mod:`drivers.gate`), the
register codec (:mod:`drivers.registers`) and the S7 count codec (:mod:`drivers.s7`).

They live apart from the classes that run them so that importing a driver module loads no
numba (``check``, ``--help`` and the configuration do not pay for a compiler): this module
is imported when the first gate or codec is built, and each module above keeps its rules,
constants and documentation; what is here is their compiled form.
"""

from __future__ import annotations

import math

import numpy as np
from numba import literal_unroll, njit, types
from numba.extending import overload

from drivers.codes import (
    AGE,
    DATA_AT,
    HEARTBEAT,
    HEARTBEAT_AT,
    INVALID,
    MODE_SCALED,
    MODE_WRAP,
    NON_FINITE,
    NOW,
    RANGE,
    S7_OVERFLOW,
    S7_UNDERFLOW,
)


# --- the output gate (drivers.gate) -------------------------------------------------------
@njit(cache=True)
def gate(lim, stamp, tension, status, wrench, counts):
    """``stamp`` (3,): now (sending), when the data was requested, when the PLC
    heartbeat last changed (-inf: never seen changing)."""
    now = stamp[NOW]
    frame = -1  # a reason that stops the whole frame
    if not 0.0 <= now - stamp[HEARTBEAT_AT] <= lim.heartbeat_timeout_s:  # NaN, -inf
        frame = HEARTBEAT
    elif not 0.0 <= now - stamp[DATA_AT] <= lim.max_input_age_s:  # no time to come
        frame = AGE
    every_channel = True
    stopped = 0
    for i in range(tension.size):
        if status[i] >= INVALID:
            status[i] = INVALID
            tension[i] = np.nan
            every_channel = False
            continue
        x = tension[i]
        reason = frame
        if reason < 0:
            if not math.isfinite(x):
                reason = NON_FINITE
            elif x < lim.tension_lo or x > lim.tension_hi:
                reason = RANGE
        if reason >= 0:
            counts[reason] += 1
            stopped += 1
            status[i] = INVALID
            tension[i] = np.nan
            every_channel = False
    if not every_channel:
        wrench[:] = np.nan
        return stopped
    reason = -1
    for k in range(wrench.size):
        w = wrench[k]
        if not math.isfinite(w):
            reason = NON_FINITE
            break
        if w < lim.wrench_lo or w > lim.wrench_hi:
            reason = RANGE
    if reason >= 0:
        counts[reason] += 1
        stopped += 1
        wrench[:] = np.nan
    return stopped


# --- S7 counts (drivers.s7) ---------------------------------------------------------------
@njit(cache=True, inline="always")
def s7_decode_count(count, newtons_per_count, min_counts, max_counts):
    """The one S7 reading: ``count`` (an int16 value) in newtons, NaN outside the window."""
    if min_counts <= count <= max_counts:
        return count * newtons_per_count
    return np.nan


@njit(cache=True, inline="always")
def s7_encode_count(newtons, newtons_per_count, min_counts, max_counts):
    """The one S7 encoding: newtons -> counts (a float holding an int16 value), rounded;
    the overflow code above the window and for NaN, the underflow code below it."""
    f = np.rint(newtons / newtons_per_count)
    if np.isnan(f) or f > max_counts:
        return float(S7_OVERFLOW)
    if f < min_counts:
        return float(S7_UNDERFLOW)
    return f


@njit(cache=True)
def s7_decode_all(words, newtons_per_count, min_counts, max_counts, out):
    for i in range(words.size):
        out[i] = s7_decode_count(np.int64(words[i]), newtons_per_count, min_counts, max_counts)


@njit(cache=True)
def s7_encode_all(newtons, newtons_per_count, min_counts, max_counts, out):
    for i in range(newtons.size):
        out[i] = s7_encode_count(newtons[i], newtons_per_count, min_counts, max_counts)


# --- the register codec (drivers.registers) ----------------------------------------------
def _size(value):  # untyped: the overload must have the same signature
    """Element count of an array; -1 for a scalar (broadcast to the field)."""
    raise NotImplementedError  # compiled only (see the overload)


def _get(value, i):
    """Element ``i`` of an array, or the scalar itself, as float64."""
    raise NotImplementedError  # compiled only (see the overload)


@overload(_size)
def _size_impl(value):
    if isinstance(value, types.Array):
        return lambda value: value.size
    return lambda value: -1


@overload(_get)
def _get_impl(value, i):
    if isinstance(value, types.Array):
        return lambda value, i: float(value[i])
    return lambda value, i: float(value)


@njit(cache=True, inline="always")
def _decode_one(u, row, bits, as_f32):
    """The value of the bits ``u`` (one 16-bit word, or two assembled high word first)
    of a field with plan ``row`` (a :data:`PLAN` record)."""
    scaled = row.mode == MODE_SCALED
    scale = row.scale if scaled else 1.0
    if row.kind == 4:
        bits[0] = u
        f = as_f32[0]
        # numpy multiplies a float32 field by a Python float scale in float32 (NEP 50)
        return float(f) if scale == 1.0 else float(f * np.float32(scale))
    if row.kind == 0 and u >= 32768:
        u -= 65536
    elif row.kind == 2 and u >= 2**31:
        u -= 2**32
    if row.s7 and scaled:
        return s7_decode_count(u, row.npc, row.s7_lo, row.s7_hi)
    return float(u) if scale == 1.0 else u * scale


@njit(cache=True, inline="always")
def _encode_one(x, row, bits, as_f32):
    """The bits stored for ``x`` in a field with plan ``row`` (a :data:`PLAN` record).

    Scaled: S7 fields through the S7 encoding; others ``x / scale``, integers rounded;
    an integer that is NaN or outside the good band becomes the field's sentinel (never
    clipped to a plausible number). Raw: as is, integers clipped to the type (the soft
    PLC's counts). Wrap: modulo the register (2**16, 2**32; 2**24 for float32).
    """
    f = x
    if row.mode == MODE_WRAP:
        if row.kind == 4:
            f = x % 16777216.0 if np.isfinite(x) else 0.0
        else:
            mask = 0xFFFF if row.kind <= 1 else 0xFFFFFFFF
            return np.int64(x if np.isfinite(x) else 0.0) & mask
    elif row.mode == MODE_SCALED:
        if row.s7:
            f = s7_encode_count(x, row.npc, row.s7_lo, row.s7_hi)
        elif row.scale != 1.0:
            f = x / row.scale
    if row.kind == 4:
        as_f32[0] = np.float32(f)
        return np.int64(bits[0])
    f = np.rint(f)
    if row.mode == MODE_SCALED and not row.s7:
        if np.isnan(f) or f < row.good_lo or f > row.good_hi:
            f = row.invalid
    elif np.isnan(f):
        f = 0.0
    f = min(max(f, row.type_lo), row.type_hi)
    return np.int64(f) & (0xFFFF if row.kind <= 1 else 0xFFFFFFFF)


@njit(cache=True)
def decode_fields(buf, plan, bits, outs):
    as_f32 = bits.view(np.float32)  # float32 bit patterns are assembled in ``bits``
    k = 0
    for out in literal_unroll(outs):
        row = plan[k]
        if out.size != row.count:
            raise ValueError("decode: an output's size differs from its field's count")
        step = 2 if row.kind <= 1 else 4
        for i in range(row.count):
            p = row.start + step * i
            u = (np.int64(buf[p]) << 8) | np.int64(buf[p + 1])
            if row.kind >= 2:
                w = (np.int64(buf[p + 2]) << 8) | np.int64(buf[p + 3])
                u = (w << 16) | u if row.swap else (u << 16) | w
            out[i] = _decode_one(u, row, bits, as_f32)
        k += 1  # noqa: SIM113 (literal_unroll has no enumerate)


@njit(cache=True)
def encode_fields(buf, plan, bits, values):
    as_f32 = bits.view(np.float32)
    k = 0
    for value in literal_unroll(values):
        row = plan[k]
        size = _size(value)
        if size >= 0 and size != row.count:
            raise ValueError("encode: a value's size differs from its field's count")
        step = 2 if row.kind <= 1 else 4
        for i in range(row.count):
            u = _encode_one(_get(value, i), row, bits, as_f32)
            p = row.start + step * i
            if row.kind <= 1:
                buf[p], buf[p + 1] = (u >> 8) & 0xFF, u & 0xFF
                continue
            hi, lo = (u >> 16) & 0xFFFF, u & 0xFFFF
            if row.swap:
                hi, lo = lo, hi
            buf[p], buf[p + 1] = (hi >> 8) & 0xFF, hi & 0xFF
            buf[p + 2], buf[p + 3] = (lo >> 8) & 0xFF, lo & 0xFF
        k += 1
