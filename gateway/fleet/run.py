"""The tasks on dask.distributed: a LocalCluster on this machine, or an existing scheduler.

One task per recording (:func:`gateway.fleet.task.diagnose_task`; with ``--per-robot`` one
per robot, its recordings a list diagnosed jointly), results taken as they
finish (a line each on ``progress``); a task that fails in Dask itself (a worker killed
over its memory limit, a lost worker) becomes an error of that recording, never the end
of the job. Workers run one task at a time (``threads_per_worker=1``; the diagnosis is
numpy and numba, one core each), so a worker's memory limit is one recording's figure
plus the worker's own: :data:`TASK_MEMORY_BYTES` (``diagnose`` of 10 min x 1 kHz x 8
cables peaks at 373 MB from CSV.gz, 422 MB from Parquet with pyarrow loaded,
docs/recording-format.md "Memory") + :data:`WORKER_BASE_BYTES` (a worker with the
libraries loaded; a worker over 95 % of its limit is restarted by Dask and that
recording is listed as failed).

Dask's own log lines in this process (the scheduler, the nannies and the client of a
LocalCluster: ~30 INFO lines per run, and at shutdown a scheduler-to-worker stream closing
under a pending write logs a ``CommClosedError`` traceback) go to ``dask.log`` in the
output directory, never to the terminal, where a line per recording is the interface;
WARNING and above are echoed to stderr, prefixed ``dask:``, while the tasks run (a worker
restarted over its memory limit is news then), and not while the cluster closes, when
nothing a user can act on is left. The workers' own processes log ERROR and above
(``silence_logs``).
"""

from __future__ import annotations

import contextlib
import logging
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from gateway.errors import GatewayError
from gateway.fleet.sizing import refusal
from gateway.fleet.task import JOIN, TaskResult, diagnose_task, group_identity

Task = str | list[str]
"""One task: a recording, or one robot's recordings diagnosed jointly (``--per-robot``)."""

TASK_MEMORY_BYTES = 400 << 20  # one diagnosis of 10 min x 1 kHz x 8 cables
WORKER_BASE_BYTES = 250 << 20  # a dask worker with numpy, scipy, numba, matplotlib loaded
WORKER_MEMORY_BYTES = TASK_MEMORY_BYTES + WORKER_BASE_BYTES
EXTRA_HINT = "pip install 'cdpr-gateway[fleet]'"


def import_distributed() -> Any:
    """``distributed``, or a one-line error naming the extra that brings it."""
    try:
        import distributed
    except ImportError as exc:
        raise GatewayError(
            f"fleet needs dask.distributed, which is not installed ({exc.name}): {EXTRA_HINT}"
        ) from None
    return distributed


def _client(distributed: Any, scheduler: str | None, workers: int) -> tuple[Any, Any, str]:
    """(client, cluster or None, a line saying where the tasks run)."""
    if scheduler is not None:
        try:
            client = distributed.Client(scheduler, timeout="20s", set_as_default=False)
        except (OSError, TimeoutError) as exc:
            raise GatewayError(f"--scheduler {scheduler}: cannot connect: {exc}") from exc
        n = len(client.scheduler_info().get("workers", {}))
        return client, None, f"scheduler {scheduler} with {n} workers"
    # a task whose worker died (over its memory limit) is not sent to the next worker: it
    # killed four in turn, with the finished results they held
    import dask

    dask.config.set({"distributed.scheduler.allowed-failures": 0})
    cluster = distributed.LocalCluster(
        n_workers=workers,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address=None,
        # no dashboard; the scheduler's HTTP server (its /metrics, which it always starts,
        # on 8787 unless told) on a free loopback port: two fleets at once never clash
        scheduler_kwargs={"dashboard": False, "dashboard_address": "127.0.0.1:0"},
        memory_limit=WORKER_MEMORY_BYTES,
        silence_logs=40,
    )
    client = distributed.Client(cluster, set_as_default=False)
    mb = WORKER_MEMORY_BYTES >> 20
    return client, cluster, f"LocalCluster of {workers} workers ({mb} MiB each) on 127.0.0.1"


def run_tasks(
    recordings: list[Task],
    model: str,
    scheduler: str | None,
    workers: int,
    progress: Callable[[int, TaskResult], None],
    log: Path | None = None,
    columns: dict[str, str] | None = None,
) -> tuple[list[TaskResult], str]:
    """Every recording's result in the order of ``recordings``, and where they ran; Dask's
    log lines of this process in ``log`` (none kept without it); ``columns``: each
    recording's columns renamed (``--columns``)."""
    distributed = import_distributed()
    with DaskLog(log).installed() as dask_log:
        return _run(distributed, recordings, model, scheduler, workers, progress, dask_log, columns)


class DaskLog:
    """The ``distributed`` logger of this process writing to a file (or nowhere) and,
    WARNING and above, to stderr while the tasks run.

    ``LocalCluster(silence_logs=...)`` sets every StreamHandler of that logger to its level
    for the cluster's life (a file handler is one), so :meth:`running` sets the levels
    again once the cluster is up; :meth:`closing` takes stderr off before it closes.
    """

    def __init__(self, path: Path | None) -> None:
        self.file: logging.Handler = (
            logging.FileHandler(path, mode="w", encoding="utf-8")
            if path is not None
            else logging.NullHandler()
        )
        self.file.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        self.terminal = logging.StreamHandler(sys.stderr)
        self.terminal.setFormatter(logging.Formatter("dask: %(levelname)s %(name)s: %(message)s"))
        self.logger = logging.getLogger("distributed")

    def running(self) -> None:
        self.file.setLevel(logging.INFO)
        self.terminal.setLevel(logging.WARNING)

    def closing(self) -> None:
        self.logger.removeHandler(self.terminal)

    @contextlib.contextmanager
    def installed(self) -> Iterator[DaskLog]:
        """Installed for the block; the logger's handlers, level and propagation restored
        after, and the file closed."""
        saved = (self.logger.handlers[:], self.logger.level, self.logger.propagate)
        self.running()
        self.logger.handlers = [self.file, self.terminal]
        self.logger.setLevel(logging.INFO)
        self.logger.propagate = False
        try:
            yield self
        finally:
            self.logger.handlers = saved[0]
            self.logger.setLevel(saved[1])
            self.logger.propagate = saved[2]
            self.file.close()


def _run(
    distributed: Any,
    recordings: list[Task],
    model: str,
    scheduler: str | None,
    workers: int,
    progress: Callable[[int, TaskResult], None],
    dask_log: DaskLog,
    columns: dict[str, str] | None = None,
) -> tuple[list[TaskResult], str]:
    client, cluster, where = _client(distributed, scheduler, workers)
    dask_log.running()
    try:
        budget = _task_budget(client)
        results: list[TaskResult | None] = [None] * len(recordings)
        done = 0
        futures = {}
        for i, rec in enumerate(recordings):
            why = refusal([Path(r) for r in rec] if isinstance(rec, list) else Path(rec), budget)
            if why is not None:  # refused before it is loaded: no worker is lost to it
                results[i] = _failed(rec, why)
                done += 1
                progress(done, results[i])  # type: ignore[arg-type]
                continue
            key = f"diagnose-{i}-{_label(rec)}"
            futures[client.submit(diagnose_task, rec, model, columns, key=key, pure=False)] = i
        # with_results: each result is fetched as its task ends, never left on a worker
        # that a later task may take down with it
        finished = distributed.as_completed(
            futures, loop=client.loop, with_results=True, raise_errors=False
        )
        for future, value in finished:
            i = futures[future]
            results[i] = value if isinstance(value, TaskResult) else _result(future, recordings[i])
            done += 1
            progress(done, results[i])  # type: ignore[arg-type]
    finally:
        dask_log.closing()
        client.close()
        if cluster is not None:
            cluster.close()
    return [r for r in results if r is not None], where


def _task_budget(client: Any) -> int:
    """Memory for one task: the smallest worker's limit less a worker's own."""
    limits = [
        w.get("memory_limit") or 0 for w in client.scheduler_info().get("workers", {}).values()
    ]
    limits = [x for x in limits if x > 0]
    return (min(limits) if limits else WORKER_MEMORY_BYTES) - WORKER_BASE_BYTES


def _label(task: Task) -> str:
    return JOIN.join(task) if isinstance(task, list) else task


def _identity(task: Task) -> tuple[str, str]:
    paths = [Path(r) for r in task] if isinstance(task, list) else [Path(task)]
    return group_identity(paths, [{} for _ in paths])


def _failed(recording: Task, error: str) -> TaskResult:
    robot, start = _identity(recording)
    joined = tuple(recording) if isinstance(recording, list) else ()
    return TaskResult(_label(recording), robot, start, None, error, 0.0, "", 0.0, joined)


def _result(future: Any, recording: Task) -> TaskResult:
    t0 = time.perf_counter()
    try:
        res: TaskResult = future.result()
        return res
    except Exception as exc:  # the task never returned: a lost or killed worker
        robot, start = _identity(recording)
        return TaskResult(
            _label(recording),
            robot,
            start,
            None,
            f"{type(exc).__name__}: {exc}",
            time.perf_counter() - t0,
            "",
            0.0,
            tuple(recording) if isinstance(recording, list) else (),
        )
