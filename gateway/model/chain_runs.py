"""Running the chain over samples: one batch runner and the per-cycle stepper.

:func:`run` takes the chain (:class:`gateway.model.chain_schema.ChainParams`) over (N, m)
tensions and velocities, either way: ``compensate`` (sensor reading and setpoint velocity
-> platform tension, what the gateway does each cycle) or ``simulate`` (platform tension
-> sensor reading, the plant); ``run(p, "compensate", run(p, "simulate", T, ...), ...)``
returns ``T``. Whatever a caller keeps of the output, the kernels run over every sample
in order, :data:`BATCH_ROWS` rows per call (the travel array bounded), so every option
gives the same values bit for bit: the whole (N, m) array (into ``out`` if given), only
the samples ``rows``, or the ``pieces`` batch by batch (a caller that stops early or
reduces each batch holds no (N, m) array). :class:`ChainStepper` is the per-cycle form:
one sample of every cable on preallocated buffers. The law is in
:mod:`gateway.model.chain_kernels` (physics.md sec. 2, 3).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Literal, overload

import numpy as np

from gateway.fastcall import entry_point
from gateway.model.chain_kernels import (
    _compensate_plain,
    _plain,
    _simulate_plain,
    compensate_kernel,
    simulate_kernel,
    travel_into,
)
from gateway.model.chain_schema import ChainParams, ChainState, kernel_params

Direction = Literal["compensate", "simulate"]
"""``compensate``: sensor -> platform (implicit, Newton per pulley); ``simulate``:
platform -> sensor (explicit but for a stretching cable)."""
Piece = tuple[int, int, np.ndarray]
"""``(a, b, out[a:b])``: a batch of rows of a run's output."""
Previous = tuple[float, np.ndarray]
"""The sample before a run's first, from the run before it: its time (s) and velocity (m,)."""

BATCH_ROWS = 32768  # rows per kernel call in the batch forms (bounds the travel array)


def _time_steps(t: np.ndarray | float, n_samples: int) -> np.ndarray:
    """``dt_k = t_k - t_{k-1}`` with ``dt_0 = 0`` (no travel before the first sample)."""
    if np.ndim(t) == 0:
        dt = np.full(n_samples, float(t))
        dt[0] = 0.0
        return dt
    t_arr = np.asarray(t, dtype=float)
    if t_arr.shape != (n_samples,):
        raise ValueError(f"t: expected shape ({n_samples},), got {t_arr.shape}")
    return np.concatenate(([0.0], np.diff(t_arr)))


def travel(t: np.ndarray | float, velocity: np.ndarray) -> np.ndarray:
    """Cable travel (N, m) of each step, m, for velocity (N, m) at times ``t`` (N,) or a
    constant period: :func:`gateway.model.chain_kernels.travel_into` with no travel at the
    first sample."""
    vel = np.ascontiguousarray(velocity, dtype=float)
    dx = np.empty_like(vel)
    if vel.shape[0]:
        travel_into(vel, _time_steps(t, vel.shape[0]), vel[0].copy(), dx)
    return dx


def new_state(params: ChainParams) -> ChainState:
    """Friction state of ``params``' chain: relaxed (every pulley force zero)."""
    return ChainState.relaxed(params)


@overload
def run(
    params: ChainParams,
    direction: Direction,
    tension: np.ndarray,
    velocity: np.ndarray,
    t: np.ndarray | float,
    *,
    state: ChainState | None = ...,
    previous: Previous | None = ...,
    rows: np.ndarray | None = ...,
    out: np.ndarray | None = ...,
    pieces: Literal[False] = ...,
    tol_n: float = ...,
    max_iter: int = ...,
) -> np.ndarray: ...


@overload
def run(
    params: ChainParams,
    direction: Direction,
    tension: np.ndarray,
    velocity: np.ndarray,
    t: np.ndarray | float,
    *,
    state: ChainState | None = ...,
    previous: Previous | None = ...,
    rows: None = ...,
    out: np.ndarray | None = ...,
    pieces: Literal[True],
    tol_n: float = ...,
    max_iter: int = ...,
) -> Iterator[Piece]: ...


def run(
    params: ChainParams,
    direction: Direction,
    tension: np.ndarray,
    velocity: np.ndarray,
    t: np.ndarray | float,
    *,
    state: ChainState | None = None,
    previous: Previous | None = None,
    rows: np.ndarray | None = None,
    out: np.ndarray | None = None,
    pieces: bool = False,
    tol_n: float = 1e-10,
    max_iter: int = 20,
) -> np.ndarray | Iterator[Piece]:
    """The chain over (N, m) ``tension`` and ``velocity`` at the times ``t`` (N,) in s, or
    a constant period, ``direction`` (:data:`Direction`) from ``state`` (carried in and
    updated in place; relaxed if None). The first sample has no travel, unless
    ``previous`` (:data:`Previous`) gives the sample before it: a run continued block by
    block with the state and the previous sample carried is the whole run's, value for
    value. What is kept of the output (the same values bit for bit either way):

    * by default the (N, m) output, written into ``out`` when given;
    * ``rows`` (increasing sample indices): the output at those samples only, (n, m),
      ``run(...)[rows]`` without the (N, m) array (37 MiB for a 10-min 1 kHz 8-cable
      recording);
    * ``pieces``: an iterator of :data:`Piece` in order, one per :data:`BATCH_ROWS` rows,
      computed as the caller asks for them (a caller may stop early, e.g. once the error of
      the rows done rules a trial out). With ``out`` each piece is final in ``out``; without,
      it is one buffer that the next piece overwrites (read it before asking for the next).
    """
    if direction not in ("compensate", "simulate"):
        raise ValueError(f"direction must be 'compensate' or 'simulate', got {direction!r}")
    forward = direction == "compensate"
    n = np.shape(tension)[0]
    m = params.cables
    if pieces:
        if rows is not None:
            raise ValueError("rows and pieces are two ways to keep the output: give one")
        return _pieces(params, forward, tension, velocity, t, state, previous, tol_n, max_iter, out)
    if rows is None:
        full = np.empty(np.shape(tension)) if out is None else out
        for _ in _batches(
            params, forward, tension, velocity, t, state, previous, tol_n, max_iter, full
        ):
            pass
        return full
    if out is not None:
        raise ValueError("rows keeps its own (n, m) output: out is for the whole run")
    idx = np.asarray(rows, dtype=np.intp)
    if idx.size > 1 and np.any(np.diff(idx) <= 0):
        raise ValueError("rows must be increasing")
    kept = np.empty((idx.size, m))
    buf = np.empty((max(1, min(n, BATCH_ROWS)), m))
    a = 0
    for b in _batches(
        params, forward, tension, velocity, t, state, previous, tol_n, max_iter, buf, True
    ):
        lo, hi = np.searchsorted(idx, (a, b))
        kept[lo:hi] = buf[idx[lo:hi] - a]
        a = b
    return kept


def _pieces(
    params: ChainParams,
    forward: bool,
    tension: np.ndarray,
    velocity: np.ndarray,
    t: np.ndarray | float,
    state: ChainState | None,
    previous: Previous | None,
    tol_n: float,
    max_iter: int,
    out: np.ndarray | None,
) -> Iterator[Piece]:
    """:func:`run`'s ``pieces``: into ``out`` (N, m), or one batch's rolling buffer."""
    rolling = out is None
    if out is None:
        out = np.empty((max(1, min(np.shape(tension)[0], BATCH_ROWS)), params.cables))
    a = 0
    for b in _batches(
        params, forward, tension, velocity, t, state, previous, tol_n, max_iter, out, rolling
    ):
        yield a, b, out[: b - a] if rolling else out[a:b]
        a = b


def _batches(
    params: ChainParams,
    forward: bool,
    tension: np.ndarray,
    velocity: np.ndarray,
    t: np.ndarray | float,
    state: ChainState | None,
    previous: Previous | None,
    tol_n: float,
    max_iter: int,
    out: np.ndarray,
    rolling: bool = False,
) -> Iterator[int]:
    """The runs' work into ``out`` (N, m), one kernel call per :data:`BATCH_ROWS` rows;
    yields the rows done after each call (``out[:b]`` is final). ``rolling``: ``out``
    holds one batch (``BATCH_ROWS``, m), each batch's rows from its start (the kernels
    only write ``out``)."""
    t_in = np.ascontiguousarray(tension, dtype=float)
    vel = np.ascontiguousarray(velocity, dtype=float)
    if t_in.ndim != 2 or t_in.shape[1] != params.cables or vel.shape != t_in.shape:
        raise ValueError(
            f"tension and velocity must both have shape (N, {params.cables}); "
            f"got {t_in.shape} and {vel.shape}"
        )
    f_state = new_state(params) if state is None else state
    kernel = compensate_kernel if forward else simulate_kernel
    p = kernel_params(params, tol_n, max_iter)
    n = t_in.shape[0]
    if n == 0:
        return
    dt = _time_steps(t, n)
    v_prev = vel[0].copy()
    if previous is not None:
        t_prev, v_last = previous
        dt[0] = float(t) if np.ndim(t) == 0 else float(np.asarray(t)[0]) - t_prev
        v_prev[:] = v_last
    # the travel in row blocks (the friction state and the previous velocity carried
    # across): a 10-min, 8-cable run would otherwise hold a 38 MB travel array
    dx = np.empty((min(n, BATCH_ROWS), t_in.shape[1]))
    for a in range(0, n, BATCH_ROWS):
        b = min(a + BATCH_ROWS, n)
        travel_into(vel[a:b], dt[a:b], v_prev, dx[: b - a])
        kernel(p, t_in[a:b], vel[a:b], dx[: b - a], f_state, out[: b - a] if rolling else out[a:b])
        yield b


class ChainStepper:
    """Per-cycle form: one sample for every cable on preallocated buffers.

    The friction state (:attr:`chain_state`) and the previous step's velocity (for the
    travel, :func:`travel_into`) are carried between calls. ``step`` allocates nothing. The
    first step after construction or :meth:`reset` has no previous velocity: it takes its
    own (``dx = v dt``; the batch form takes no travel at its first sample, ``dt = 0``).
    """

    def __init__(
        self,
        params: ChainParams,
        period_s: float,
        forward: bool = True,
        tol_n: float = 1e-9,
        max_iter: int = 8,
    ) -> None:
        m = params.cables
        self.params = params
        self.forward = forward
        self.period_s = float(period_s)
        self.chain_state = new_state(params)
        self.iterations = 0
        self._in = np.zeros((1, m))
        self._vel = np.zeros((1, m))
        self._out = np.zeros((1, m))
        self._dx = np.zeros((1, m))
        self._v_prev = np.zeros(m)
        self._primed = False
        self._dt = np.array([self.period_s])
        self._p = kernel_params(params, tol_n, max_iter)
        self._travel = entry_point(travel_into, self._vel, self._dt, self._v_prev, self._dx)
        # a plain chain steps its (m, n) forces directly (a view of the state): the kernel's
        # fast path without the per-call check
        if _plain(self._p):
            kernel = _compensate_plain if forward else _simulate_plain
            self._held: ChainState | np.ndarray = self.chain_state.f.reshape(m, params.pulleys)
        else:
            kernel = compensate_kernel if forward else simulate_kernel
            self._held = self.chain_state
        self._kernel = entry_point(
            kernel, self._p, self._in, self._vel, self._dx, self._held, self._out
        )

    @property
    def state(self) -> np.ndarray:
        """(m, n) friction force of each pulley (N): the sum of its state elements."""
        return self.chain_state.pulley_forces(self._p)

    def reset(self) -> None:
        """Relax every pulley (e.g. after a long outage when the real state is unknown);
        the next step has no previous velocity."""
        self.chain_state.reset()
        self._primed = False

    def step(
        self, tension: np.ndarray, velocity: np.ndarray, out: np.ndarray, dt: float = -1.0
    ) -> int:
        """Advance by ``dt`` (s; negative: the period); write the result (m,) into ``out``;
        return the Newton passes (0 when simulating)."""
        self._in[0] = tension
        self._vel[0] = velocity
        if not self._primed:
            self._v_prev[:] = self._vel[0]
            self._primed = True
        self._dt[0] = self.period_s if dt < 0.0 else dt  # own buffers: types fixed
        self._travel(self._vel, self._dt, self._v_prev, self._dx)
        self.iterations = self._kernel(
            self._p, self._in, self._vel, self._dx, self._held, self._out
        )
        out[:] = self._out[0]
        return self.iterations
