"""The plant run in a worker process, so the soft PLC's serving process only replays it.

:class:`sim_plc.plant.Plant` in its own process would hold the GIL for every step (the
chain, the effects, the noise and the A/D: 20-60 us, over 100 us one step in ten on a
busy machine) and, every 250th step, for the statics of the next chunk (1.4-2.1 ms): the
Modbus server thread, which needs the same GIL, stalled that long.

:class:`ChunkWorker` runs the plant itself, a whole :class:`~sim_plc.plant.Plant` stepped
sample by sample in a separate process (``spawn``: no threads or locks of the parent are
inherited), ``chunk`` samples at a time, and hands over what a step of the serving
process writes into its process image (``t``, ``pose``, ``length``, ``velocity``,
``mass``, ``tension_true``, the ``analog`` reading and the A/D ``counts``: ~80 kB per 250
samples). The plant is open loop (nothing the gateway writes changes it), so it can run
ahead. The samples live in shared memory (``RawArray``, ``ahead + 3`` slots): the worker
writes chunk ``i`` into slot ``i % slots`` and sends only a note ``(i, error length)``:
nothing is copied or unpickled in the serving process; requests and notes are fixed-size
records on a socket, read without blocking (a few system calls per chunk). ``get(i)``
returns chunk ``i`` and asks for the next ``ahead`` chunks, so a chunk is normally ready
long before it is needed; when it is not (start-up, an overloaded machine) ``get`` waits
and counts it in ``waits``. A request for an earlier chunk than the worker's plant has
reached (the serving plant was reset) restarts the worker's plant from t = 0. An error of
the worker (an infeasible pose) is raised by ``get`` for the chunk it concerns.

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
import signal
import struct
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from gateway.core.config import Config
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


@contextlib.contextmanager
def _no_sigint() -> Iterator[None]:
    """SIGINT ignored while a worker process starts (from the main thread): an ignored
    signal stays ignored across exec, and Python then installs no KeyboardInterrupt handler
    in the child, so a Ctrl-C at the terminal (sent to the whole process group) no longer
    printed 'Process sim-plc-chunks: Traceback ... KeyboardInterrupt'; the parent stops it."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


# what a step of the serving process writes into its image, per sample
FIELDS = ("t", "pose", "length", "velocity", "mass", "tension_true", "analog", "counts")


@dataclass
class Chunk:
    """One chunk of plant samples (views of a shared-memory slot; rows are samples)."""

    t: np.ndarray
    pose: np.ndarray
    length: np.ndarray
    velocity: np.ndarray
    mass: np.ndarray
    tension_true: np.ndarray
    analog: np.ndarray
    counts: np.ndarray  # float64 holding the int16 A/D counts exactly


def _slot_views(raw: Any, slots: int, chunk: int, cables: int) -> list[dict[str, np.ndarray]]:
    """Numpy views of each slot of the shared buffer: one array per field of FIELDS."""
    shapes = {
        "t": (chunk,),
        "pose": (chunk, 6),
        "length": (chunk, cables),
        "mass": (chunk,),
        "velocity": (chunk, cables),
        "tension_true": (chunk, cables),
        "analog": (chunk, cables),
        "counts": (chunk, cables),
    }
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
    return chunk * (1 + 6 + 1 + 5 * cables)


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


def _run_chunk(plant: Any, image: Any, slot: dict[str, np.ndarray]) -> None:
    """Step ``plant`` through one chunk, each sample's image values into ``slot``."""
    for j in range(plant.chunk):
        plant.step(image)
        slot["t"][j] = image.time_s
        slot["pose"][j] = image.pose
        slot["length"][j] = image.length_m
        slot["velocity"][j] = image.velocity_m_s
        slot["mass"][j] = image.platform_mass_kg
        slot["tension_true"][j] = image.true_tension_n
        slot["analog"][j] = plant.analog
        slot["counts"][j] = plant.counts


def _worker(
    conn: Connection, raw: Any, slots: int, cfg: Config, sim: SimPlcConfig, chunk: int
) -> None:
    """Serve chunk indices (int64 requests on ``conn``'s socket; -1 or EOF: stop): chunk
    ``i`` of the plant's run is written into slot ``i % slots`` of ``raw``, then a note
    ``(i, n)`` is sent, followed by ``n`` bytes of the pickled exception when it failed
    (n > 0). The plant runs forward only; an earlier index restarts it from t = 0."""
    _background()
    from sim_plc.image import ProcessImage  # here: the parent's plant.py imports this module
    from sim_plc.plant import Plant

    fd = conn.fileno()
    plant = Plant(cfg, sim, chunk)
    image = ProcessImage(plant.model.cables)
    views = _slot_views(raw, slots, chunk, plant.model.cables)
    scratch = _slot_views(
        np.zeros(slot_doubles(chunk, plant.model.cables)), 1, chunk, plant.model.cables
    )[0]
    done = 0  # chunks the plant has run
    while (request := _read_exact(fd, _REQUEST.size)) is not None:
        index = _REQUEST.unpack(request)[0]
        if index < 0:
            return
        error = b""
        try:
            if index < done:
                plant.reset()
                done = 0
            while done < index:  # not in normal use: requests come in order
                _run_chunk(plant, image, scratch)
                done += 1
            _run_chunk(plant, image, views[index % slots])
            done += 1
        except Exception as exc:  # raised by get()
            error = pickle.dumps(exc)
            plant.reset()
            done = 0
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
        with _no_sigint():  # the worker inherits SIGINT ignored: a Ctrl-C is the parent's
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

    def get(self, index: int) -> Chunk:
        """Chunk ``index`` (views of shared memory), valid until ``get(index + 2)``."""
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
        return Chunk(**self._views[index % self.slots])

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
