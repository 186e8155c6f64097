"""Plant chunks prepared in a worker process, so the soft PLC's serving process never does.

:class:`sim_plc.plant.Plant` steps through chunks of ``chunk`` samples whose setpoints and
statics (kinematics, wrench, one tension distribution per sample) are computed ahead.
Done in the PLC's own process, that preparation held the GIL for 1.4-2.1 ms every 250th
step: the Modbus server thread, which needs the same GIL, stalled that long (issue 12).

:class:`ChunkWorker` computes them in a separate process (``spawn``: no threads or locks
of the parent are inherited), only the arrays a step reads (``t``, ``pose``, ``length``,
``velocity``, ``mass``, ``tension_true``: ~60 kB per 250 samples). They live in shared memory
(``RawArray``, ``ahead + 3`` slots): the worker writes chunk ``i`` into slot
``i % slots`` and sends only a note ``(i, error length)``: nothing is copied or
unpickled in the serving process; requests and notes are fixed-size records on a socket,
read without blocking (a few system calls per chunk). ``get(i)`` returns chunk ``i`` and
asks for the next ``ahead`` chunks, so a chunk is normally ready long before it is
needed; when it is not (start-up, an overloaded machine) ``get`` waits and counts it in
``waits``. An error of the worker (an infeasible pose) is raised by ``get`` for the chunk
it concerns.

The worker gives up any real-time setting it inherited (SCHED_OTHER, every CPU): it is
background work and must not compete with the cycle it feeds. Under real-time settings the
soft PLC puts it at SCHED_FIFO priority 1 (:meth:`ChunkWorker.lowest_realtime`): a chunk
costs ~50 ms of CPU per 250 ms, which a normal-priority process did not get on a loaded
machine.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import pickle
import select
import struct
import time
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from gateway.config import Config
from gateway.errors import GatewayError
from sim_plc.config import SimPlcConfig

START_TIMEOUT_S = 60.0  # a chunk (or the worker's start-up) that takes longer is an error
_REQUEST = struct.Struct("<q")  # chunk index; -1: stop
_NOTE = struct.Struct("<qq")  # chunk index, length of the pickled error that follows


def _background() -> None:
    """Drop inherited real-time scheduling and CPU pinning (best effort). Not niced: on a
    loaded machine a niced worker starved and the plant waited for its chunks."""
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setaffinity(0, range(os.cpu_count() or 1))


FIELDS = ("t", "pose", "length", "velocity", "mass", "tension_true")  # what Plant.step reads


def _slot_views(raw: Any, slots: int, chunk: int, cables: int) -> list[dict[str, np.ndarray]]:
    """Numpy views of each slot of the shared buffer: one array per field of FIELDS."""
    shapes = {"t": (chunk,), "pose": (chunk, 6), "length": (chunk, cables), "mass": (chunk,),
              "velocity": (chunk, cables), "tension_true": (chunk, cables)}  # fmt: skip
    flat = np.frombuffer(raw, dtype=np.float64)
    views, off = [], 0
    for _ in range(slots):
        slot = {}
        for name in FIELDS:
            n = int(np.prod(shapes[name]))
            slot[name] = flat[off : off + n].reshape(shapes[name])
            off += n
        views.append(slot)
    return views


def slot_doubles(chunk: int, cables: int) -> int:
    return chunk * (1 + 6 + 1 + 3 * cables)


def _read_exact(fd: int, n: int) -> bytes | None:
    """``n`` bytes from blocking ``fd``; None at EOF."""
    out = b""
    while len(out) < n:
        try:
            part = os.read(fd, n - len(out))
        except OSError:
            return None
        if not part:
            return None
        out += part
    return out


def _worker(conn: Connection, raw: Any, slots: int, cfg: Config, sim: SimPlcConfig,
            chunk: int) -> None:  # fmt: skip
    """Serve chunk indices (int64 requests on ``conn``'s socket; -1 or EOF: stop): chunk
    ``i`` is written into slot ``i % slots`` of ``raw``, then a note ``(i, n)`` is sent,
    followed by ``n`` bytes of the pickled exception when it failed (n > 0)."""
    _background()
    from sim_plc.plant import PlantModel  # here: the parent's plant.py imports this module

    fd = conn.fileno()
    model = PlantModel(cfg, sim)
    views = _slot_views(raw, slots, chunk, model.cables)
    period = model.sim.period_s
    while (request := _read_exact(fd, _REQUEST.size)) is not None:
        index = _REQUEST.unpack(request)[0]
        if index < 0:
            return
        t = (index * chunk + np.arange(chunk)) * period
        error = b""
        try:
            sp = model.setpoints(t)
            for name in FIELDS:
                views[index % slots][name][...] = getattr(sp, name)
        except Exception as exc:  # raised by get()
            error = pickle.dumps(exc)
        try:
            os.write(fd, _NOTE.pack(index, len(error)) + error)
        except OSError:
            return


class ChunkWorker:
    """Solved plant chunks from a worker process; ``get(i)``, ``close()`` (safe twice)."""

    def __init__(self, cfg: Config, sim: SimPlcConfig, chunk: int, ahead: int = 4) -> None:
        self.cfg, self.sim, self.chunk, self.ahead = cfg, sim, int(chunk), max(int(ahead), 1)
        # slots: the current chunk, the next, ``ahead`` in flight, one just released
        self.slots = self.ahead + 3
        self.waits = 0  # get() calls that had to wait for the worker
        self._conn: Connection | None = None
        self._fd = -1
        self._proc: Any = None
        self._views: list[dict[str, np.ndarray]] = []
        self._asked: set[int] = set()
        self._ready: dict[int, bytes] = {}  # index -> pickled error (b"": fine)
        self._rx = bytearray()
        self._last = -1

    def start(self) -> ChunkWorker:
        from sim_plc.plant import Setpoints

        self._setpoints = Setpoints
        ctx = mp.get_context("spawn")
        cables = self.cfg.cables
        raw = ctx.RawArray("d", self.slots * slot_doubles(self.chunk, cables))
        self._views = _slot_views(raw, self.slots, self.chunk, cables)
        mine, theirs = ctx.Pipe()
        proc = ctx.Process(
            target=_worker,
            args=(theirs, raw, self.slots, self.cfg, self.sim, self.chunk),
            name="sim-plc-chunks",
            daemon=True,
        )
        proc.start()
        theirs.close()
        self._conn, self._proc, self._fd = mine, proc, mine.fileno()
        os.set_blocking(self._fd, False)
        return self

    def lowest_realtime(self) -> tuple[bool, str]:
        """Run the worker at SCHED_FIFO priority 1: above every normal task, below any
        cycle thread (the soft PLC's run at the configured priority, e.g. 50). For a
        soft PLC under real-time settings: on a loaded machine a normal-priority worker
        got less than the ~20 % of a core it needs and the plant waited for chunks.
        Returns (done, what), for the caller's report line."""
        what = "chunk worker SCHED_FIFO priority 1"
        if self._proc is None or self._proc.pid is None:
            return False, f"{what}: the worker is not running"
        try:
            os.sched_setscheduler(self._proc.pid, os.SCHED_FIFO, os.sched_param(1))
        except OSError as exc:
            return False, f"{what}: {exc.strerror or exc}"
        return True, what

    def _ask(self, first: int, last: int) -> None:
        """Request the chunks ``first .. last`` not yet asked for or ready (one write)."""
        new = [k for k in range(first, last + 1) if k not in self._asked and k not in self._ready]
        if new:
            os.write(self._fd, b"".join(_REQUEST.pack(k) for k in new))
            self._asked.update(new)

    def _drain(self) -> None:
        """Take every note the worker has sent so far (non-blocking)."""
        while True:
            try:
                part = os.read(self._fd, 65536)
            except BlockingIOError:
                break
            if not part:
                raise GatewayError("plant chunk worker: ended unexpectedly")
            self._rx += part
        rx = self._rx
        while len(rx) >= _NOTE.size:
            index, n = _NOTE.unpack_from(rx)
            if len(rx) < _NOTE.size + n:
                break
            self._ready[index] = bytes(rx[_NOTE.size : _NOTE.size + n])
            self._asked.discard(index)
            del rx[: _NOTE.size + n]

    def _wait_for(self, index: int) -> None:
        deadline = time.monotonic() + START_TIMEOUT_S
        while index not in self._ready:
            rest = deadline - time.monotonic()
            if rest <= 0 or not select.select([self._fd], [], [], rest)[0]:
                raise GatewayError(
                    f"plant chunk worker: chunk {index} not ready after {START_TIMEOUT_S:g} s"
                )
            self._drain()

    def _restart(self) -> None:
        """Indices went back (the plant was reset): let every chunk in flight land first,
        so none is written into a slot that is in use again."""
        while self._asked:
            self._wait_for(next(iter(self._asked)))
        self._ready.clear()

    def get(self, index: int) -> Any:
        """Chunk ``index`` as ``Setpoints`` (views of shared memory; only the fields a
        step reads, the others empty), valid until ``get(index + 2)``."""
        if self._fd < 0:
            raise GatewayError("plant chunk worker: not started or closed")
        if index < self._last:
            self._restart()
        self._last = index
        self._ask(index, index + self.ahead)
        self._drain()
        if index not in self._ready:
            self.waits += 1
            self._wait_for(index)
        error = self._ready.pop(index)
        for stale in [k for k in self._ready if k < index]:
            del self._ready[stale]
        if error:
            raise pickle.loads(error)
        v, empty = self._views[index % self.slots], np.empty(0)
        return self._setpoints(
            v["t"], v["pose"], v["length"], v["velocity"], empty, v["mass"], empty, empty,
            v["tension_true"], empty,
        )  # fmt: skip

    def close(self, timeout_s: float = 5.0) -> None:
        conn, proc = self._conn, self._proc
        self._conn = self._proc = None
        if conn is not None:
            with contextlib.suppress(OSError):
                os.write(self._fd, _REQUEST.pack(-1))
            self._fd = -1
            conn.close()
        if proc is not None:
            proc.join(timeout_s)
            if proc.is_alive():
                proc.terminate()
                proc.join(timeout_s)
            proc.close()

    def __enter__(self) -> ChunkWorker:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
