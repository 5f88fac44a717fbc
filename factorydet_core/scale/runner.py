"""Run a frame job over many frames: in this process (the default, no Ray needed), or streamed
through Ray workers that each set the job up once (a local Ray, or a cluster by address).

Either way each frame's result is written to its own file in the output folder as soon as it is
computed (atomically: a file is whole or absent), so a re-run skips the frames already done, a
worker killed mid-frame costs only that frame's redo, and the driver holds no frame: it hands out
frame indices and receives one small row per frame. A job writes the same bytes for a frame
wherever it runs, so the two paths give the same outputs.
"""

from __future__ import annotations

import collections
import ctypes
import dataclasses
import json
import logging
import os
import resource
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from factorydet_core.io.atomic import write_text_atomic
from factorydet_core.io.jsonfile import read_json
from factorydet_core.threads import available_cores, configure_threads
from factorydet_core.types import MAX_RAY_WORKERS, FrameLostError, InputError

JOB_FILE = "job.json"
"""The output folder's description of the job that writes it: a re-run must be the same job."""
SUMMARY_FILE = "summary.json"
FRAMES_DIR = "frames"

RAY_VERSION = "2.60.0"
"""The Ray release the project pins (``pyproject.toml``'s ``scale`` extra); a cluster runs the same."""


class FrameJob(Protocol):
    """Work done frame by frame. It must pickle (Ray ships it to its workers) and be cheap until
    ``setup``; ``run`` must write ``out_path`` atomically and compute the same bytes wherever it
    runs."""

    kind: str

    def describe(self) -> dict:
        """What the outputs depend on, JSON-able: a re-run into the same folder must match it."""

    def setup(self) -> None:
        """Load what every frame needs (a model, the data set); once per worker."""

    def run(self, frame_index: int, out_path: Path) -> dict[str, float]:
        """Compute frame ``frame_index`` and write it to ``out_path``; returns a few numbers about it."""


class SetUpOnce:
    """What every frame job shares: its settings travel to the workers by pickle, what it loads
    (``load``: a model, a data set, a simulator) does not; ``loaded()`` loads on first use, in
    whichever process runs the job."""

    _loaded: Any = None

    def load(self) -> Any:
        """What every frame needs (a subclass says); called once per process."""
        raise NotImplementedError

    def setup(self) -> None:
        self._loaded = self.load()

    def loaded(self) -> Any:
        if self._loaded is None:
            self.setup()
        return self._loaded

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "_loaded"}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._loaded = None


@dataclasses.dataclass(frozen=True)
class Execution:
    """Where batch work runs: the ``--workers`` / ``--ray`` switch of the batch commands.

    Args:
        workers: Ray workers (actors), each with its own copy of the job and ``threads`` threads.
            ``None`` with no ``ray_address``: this process does the work itself (the default).
        ray_address: ``None`` (a local Ray when ``workers`` is given), ``"local"`` (start one),
            ``"auto"`` (the cluster this machine belongs to, ``ray start``) or ``"HOST:PORT"``.
        threads: threads per Ray worker (``threads.configure_threads``).
    """

    workers: int | None = None
    ray_address: str | None = None
    threads: int = 1
    scratch: str | None = None
    """Where commands without an output folder of their own (``train``'s proposals, ``evaluate``
    without ``--out``) keep their frames' files: a folder every node of a cluster sees. ``None``:
    ``$TMPDIR``, which only a single machine's workers share."""

    def __post_init__(self) -> None:
        workers = self.workers
        if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int)):
            raise InputError(f"Ray workers must be a whole number, got {workers!r}")
        if workers is not None and not 1 <= workers <= MAX_RAY_WORKERS:
            raise InputError(f"Ray workers must be in [1, {MAX_RAY_WORKERS}], got {workers}")
        if (
            isinstance(self.threads, bool)
            or not isinstance(self.threads, int)
            or not 1 <= self.threads <= 256
        ):
            raise InputError(f"threads per Ray worker must be in [1, 256], got {self.threads!r}")
        if self.ray_address is not None and not str(self.ray_address).strip():
            raise InputError("a Ray address is 'local', 'auto' or HOST:PORT, not blank")

    @property
    def uses_ray(self) -> bool:
        return self.workers is not None or self.ray_address is not None

    def describe(self) -> dict:
        return {"ray": self.uses_ray, "workers": self.workers, "address": self.ray_address}

    def arguments(self) -> list[str]:
        """The batch commands' flags that give this execution (for a command run in a child
        process); none for this process alone."""
        if not self.uses_ray:
            return []
        flags = ["--worker-threads", str(self.threads)]
        if self.workers is not None:
            flags += ["--workers", str(self.workers)]
        if self.ray_address is not None:
            flags += ["--ray", str(self.ray_address)]
        if self.scratch is not None:
            flags += ["--scratch", str(self.scratch)]
        return flags

    def scratch_folder(self, prefix: str) -> tempfile.TemporaryDirectory:
        """A temporary folder under ``scratch`` (``$TMPDIR`` by default), removed on exit."""
        if self.scratch is not None and not Path(self.scratch).is_dir():
            raise InputError(f"the scratch folder {self.scratch} does not exist")
        return tempfile.TemporaryDirectory(prefix=prefix, dir=self.scratch)


@dataclasses.dataclass(frozen=True)
class BatchRun:
    """What ``run_frames`` did."""

    out_dir: Path
    frames: tuple[int, ...]
    """Every frame the run covers, done now or before."""
    computed: tuple[int, ...]
    """The frames computed by this run, in the order they finished."""
    skipped: tuple[int, ...]
    """The frames whose output was there already (a resumed run)."""
    seconds: float
    """Wall time from handing out the first frame to receiving the last: the workers' set-up (a
    model loaded) included, starting or joining Ray not (``startup_seconds``)."""
    startup_seconds: float
    workers: int
    frame_seconds: tuple[float, ...]
    """Each computed frame's own time in its worker, in ``computed``'s order."""
    driver_peak_rss_mb: float
    worker_peak_rss_mb: float
    """The largest peak resident memory any worker reported (this process's, in-process)."""
    worker_pids: tuple[int, ...]
    node_ids: tuple[str, ...] = ()
    """The Ray nodes that computed frames (none in-process)."""

    @property
    def frames_per_second(self) -> float:
        return len(self.computed) / self.seconds if self.seconds > 0 else float("nan")

    def summary(self) -> dict:
        return {
            "out": str(self.out_dir),
            "num_frames": len(self.frames),
            "num_computed": len(self.computed),
            "num_skipped": len(self.skipped),
            "workers": self.workers,
            "seconds": round(self.seconds, 2),
            "startup_seconds": round(self.startup_seconds, 2),
            "frames_per_second": round(self.frames_per_second, 3),
            "median_frame_seconds": round(float(np.median(self.frame_seconds)), 3)
            if self.frame_seconds
            else None,
            "driver_peak_rss_mb": round(self.driver_peak_rss_mb, 1),
            "worker_peak_rss_mb": round(self.worker_peak_rss_mb, 1),
            "num_nodes": len(self.node_ids),
        }


def frame_path(out_dir: str | os.PathLike, frame_index: int) -> Path:
    """Where a job writes frame ``frame_index``'s result."""
    return Path(out_dir) / FRAMES_DIR / f"frame_{int(frame_index):05d}.npz"


def done_frames(out_dir: str | os.PathLike, frames: Sequence[int]) -> list[int]:
    """The frames of ``frames`` whose result is in ``out_dir`` (whole: files are written atomically)."""
    return [int(i) for i in frames if frame_path(out_dir, i).is_file()]


def peak_rss_mb() -> float:
    """This process's peak resident memory (Linux reports kilobytes)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _prepare(job: FrameJob, out_dir: Path) -> None:
    """Create the output folder, or check that the job that wrote it is this one."""
    description = {"kind": job.kind, **job.describe()}
    job_file = out_dir / JOB_FILE
    if job_file.is_file():
        before = read_json(job_file, what="batch job description")
        if not isinstance(before, dict):
            raise InputError(f"{job_file}: not a batch job description; delete the folder to start again")
        if before != json.loads(json.dumps(description)):
            changed = sorted(k for k in set(before) | set(description) if before.get(k) != description.get(k))
            raise InputError(
                f"{out_dir} holds the results of another job (it differs in: {', '.join(changed)}); "
                "write to another folder, or delete this one to start again"
            )
    elif out_dir.exists() and any(out_dir.iterdir()):
        raise InputError(f"{out_dir} exists and is not a batch output folder; give an empty or new folder")
    (out_dir / FRAMES_DIR).mkdir(parents=True, exist_ok=True)
    if not job_file.is_file():
        write_text_atomic(job_file, json.dumps(description, indent=1, sort_keys=True) + "\n")
    remove_temporaries(out_dir)


def remove_temporaries(out_dir: Path) -> None:
    """Delete the hidden half-written files (``io.atomic``) a killed writer left in the frames
    folder; only while no worker writes there (before and after a run)."""
    for path in (out_dir / FRAMES_DIR).glob(".frame_*.tmp*"):
        path.unlink(missing_ok=True)


def release_free_heap() -> None:
    """Hand the C heap's free pages back to the system (glibc's ``malloc_trim``); nothing where
    the C library is not glibc.

    A frame's large numpy temporaries are freed when it is done, but glibc keeps much of that
    memory mapped, in pieces the next frame's arrays do not fit: without this a worker's resident
    memory creeps up frame after frame (``docs/scaling.md``, Memory).
    """
    if _malloc_trim is not None:
        _malloc_trim(0)


def _find_malloc_trim() -> Callable[[int], int] | None:
    try:
        return ctypes.CDLL(None).malloc_trim  # the C library this process runs on
    except (OSError, AttributeError):  # not glibc (musl, macOS)
        return None


_malloc_trim = _find_malloc_trim()


def run_one(job: FrameJob, frame_index: int, out_dir: str | os.PathLike) -> dict[str, float]:
    """One frame on whatever process runs it: the job's row plus its timing, process and memory
    (the heap's free pages handed back after it, ``release_free_heap``)."""
    start = time.perf_counter()
    row = dict(job.run(int(frame_index), frame_path(out_dir, frame_index)))
    release_free_heap()
    row.update(
        frame_index=int(frame_index),
        seconds=time.perf_counter() - start,
        pid=os.getpid(),
        peak_rss_mb=peak_rss_mb(),
    )
    return row


def run_frames(
    job: FrameJob,
    frames: Sequence[int],
    out_dir: str | os.PathLike,
    execution: Execution = Execution(),
    progress: Callable[[int, int], None] | None = None,
    on_row: Callable[[dict[str, Any]], None] | None = None,
) -> BatchRun:
    """Run ``job`` on every frame of ``frames`` not done yet in ``out_dir``.

    Args:
        job: the per-frame work (``jobs``).
        frames: frame indices, each at most once.
        out_dir: the output folder: new, empty, or one this same job wrote (it resumes).
        execution: in this process (default) or on Ray workers.
        progress: called as ``progress(frames_done, num_frames)`` (skipped frames count as done).
        on_row: called with each computed frame's row as it arrives (its ``frame_index``,
            ``seconds``, ``pid``, ``peak_rss_mb`` and the job's own numbers).

    Raises:
        InputError: a repeated frame, a folder of another job, Ray missing or unreachable.
        FrameLostError: a frame that kept killing its Ray worker (``FRAME_ATTEMPTS``).
    """
    frames = [int(i) for i in frames]
    if len(set(frames)) != len(frames):
        raise InputError("a frame is listed twice")
    # Absolute: a Ray worker's working folder is not the driver's.
    out_dir = Path(out_dir).resolve()
    _prepare(job, out_dir)
    skipped = done_frames(out_dir, frames)
    already = set(skipped)
    todo = [i for i in frames if i not in already]
    report = progress or (lambda done, total: None)
    report(len(skipped), len(frames))

    computed: list[int] = []
    frame_seconds: list[float] = []
    pids: set[int] = set()
    nodes: set[str] = set()
    worker_peak = 0.0

    def take(row: dict[str, Any]) -> None:
        nonlocal worker_peak
        computed.append(int(row["frame_index"]))
        frame_seconds.append(float(row["seconds"]))
        pids.add(int(row["pid"]))
        if "node_id" in row:
            nodes.add(str(row["node_id"]))
        worker_peak = max(worker_peak, float(row["peak_rss_mb"]))
        if on_row is not None:
            on_row(row)
        report(len(skipped) + len(computed), len(frames))

    startup = time.perf_counter()
    workers = 0
    rows: Iterator[dict[str, Any]] = iter(())
    if todo and execution.uses_ray:
        rows, workers = _ray_rows(job, todo, out_dir, execution)
    elif todo:
        rows, workers = _local_rows(job, todo, out_dir), 1
    startup_seconds = time.perf_counter() - startup
    start = time.perf_counter()
    try:
        for row in rows:
            take(row)
    except Exception as exc:
        raise _input_error_inside(exc) or exc from None
    finally:
        # A cancel (a progress callback that raises) stops the run: the Ray workers are stopped with
        # the rows' iterator, before a caller removes a temporary output folder.
        close = getattr(rows, "close", None)
        if close is not None:
            close()
    seconds = time.perf_counter() - start
    if todo and not execution.uses_ray:
        worker_peak = max(worker_peak, peak_rss_mb())
    remove_temporaries(out_dir)
    run = BatchRun(
        out_dir=out_dir,
        frames=tuple(frames),
        computed=tuple(computed),
        skipped=tuple(skipped),
        seconds=seconds,
        startup_seconds=startup_seconds,
        workers=workers,
        frame_seconds=tuple(frame_seconds),
        driver_peak_rss_mb=peak_rss_mb(),
        worker_peak_rss_mb=worker_peak,
        worker_pids=tuple(sorted(pids)),
        node_ids=tuple(sorted(nodes)),
    )
    missing = [i for i in frames if not frame_path(out_dir, i).is_file()]
    if missing:  # never expected: Ray retries a dead worker's frames and raises when it gives up
        raise RuntimeError(f"{len(missing)} frames have no result after the run (first: {missing[0]})")
    write_text_atomic(
        out_dir / SUMMARY_FILE,
        json.dumps({**run.summary(), "execution": execution.describe()}, indent=1) + "\n",
    )
    return run


def _local_rows(job: FrameJob, todo: list[int], out_dir: Path) -> Iterator[dict[str, Any]]:
    """Rows of ``todo``'s frames computed here, the job set up when the first is asked for (as a
    Ray worker sets up inside the timed run, so that both paths' frames per second compare)."""
    job.setup()
    for i in todo:
        yield run_one(job, i, out_dir)


def _input_error_inside(exc: BaseException) -> InputError | None:
    """The ``InputError`` a worker raised, out of the Ray errors wrapping it (a data set missing on
    a node, a model of other classes): the command line then says it in one line."""
    seen: set[int] = set()
    pending: list[BaseException | None] = [exc]
    while pending:
        error = pending.pop()
        if error is None or id(error) in seen:
            continue
        seen.add(id(error))
        if isinstance(error, InputError):
            return InputError(str(error))
        pending += [error.__cause__, error.__context__, getattr(error, "cause", None)]
    return None


class _RayWorker:
    """A Ray actor: sets the job up once, then computes the frames it is handed one by one."""

    def __init__(self, job: FrameJob, out_dir: str, threads: int) -> None:
        configure_threads(threads)
        self.job = job
        self.out_dir = out_dir
        self.setup_error: Exception | None = None
        try:
            job.setup()
        except Exception as exc:
            # Raised by ``run``: a task's error carries the exception itself to the driver (an
            # actor's failed creation only its text), and ends the run instead of a restart.
            self.setup_error = exc

    def run(self, frame_index: int) -> dict[str, Any]:
        import ray

        if self.setup_error is not None:
            raise self.setup_error

        node_id = ray.get_runtime_context().get_node_id()
        return {**run_one(self.job, frame_index, self.out_dir), "node_id": node_id}


_started_with: dict[str, Any] | None = None
"""How this process started or joined Ray (``connect_ray``); ``None`` when it did not, or when
something else (a test, a notebook) did."""

FORWARDED_ENVIRONMENT = ("FACTORYDET_MAX_POINTS", "FACTORYDET_MAX_READ_BYTES")
"""The readers' caps (``io.limits``), passed to every Ray worker: a data set read here under raised
caps must read the same on a cluster's other nodes."""


def connect_ray(execution: Execution) -> int:
    """Start or join Ray as ``execution`` says; returns the workers to use: ``execution.workers``,
    or the cluster's CPUs over the threads per worker. A Ray this process started for other
    settings (another address, fewer CPUs) is stopped and started again."""
    global _started_with
    try:
        import ray
    except ImportError:
        raise InputError(
            f"Ray workers need Ray: pip install 'ray=={RAY_VERSION}' (make's set-up installs it)"
        ) from None
    # Ray's own usage report stays off unless a user turned it on.
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    address = execution.ray_address
    options: dict[str, Any] = {
        "include_dashboard": False,
        "log_to_driver": False,
        "logging_level": logging.WARNING,
        "runtime_env": {"env_vars": {k: os.environ[k] for k in FORWARDED_ENVIRONMENT if k in os.environ}},
    }
    if address in (None, "local"):
        # "local" makes Ray start its own, whatever RAY_ADDRESS or an earlier `ray start` says.
        cores = (execution.workers * execution.threads) if execution.workers else available_cores()
        options.update(address="local", num_cpus=cores)
    else:
        options["address"] = address
    if ray.is_initialized() and _started_with is not None and _started_with != options:
        ray.shutdown()
        _started_with = None
    if not ray.is_initialized():
        try:
            ray.init(**options)
        except (ConnectionError, ValueError) as exc:
            raise InputError(f"Ray at {address or 'local'}: {exc}") from None
        _started_with = options
    if execution.workers is not None:
        return execution.workers
    cpus = int(ray.cluster_resources().get("CPU", 1))
    return max(1, cpus // execution.threads)


IN_FLIGHT_PER_WORKER = 2
"""Frames handed to a worker at once: the one it computes and the next, so that it never waits for
the driver; a killed worker costs at most these."""

FRAME_ATTEMPTS = 4
"""Times a frame is given to a worker (Ray's ``max_task_retries`` is one less). A worker that dies
(killed, out of memory, a crash in native code) is restarted by Ray and computes the frames it
held again; a frame that kills every worker it is given would otherwise go on for ever."""


def _ray_rows(
    job: FrameJob, todo: list[int], out_dir: Path, execution: Execution
) -> tuple[Iterator[dict[str, Any]], int]:
    """Rows of ``todo``'s frames as Ray workers finish them.

    Plain Ray actors, each holding ``IN_FLIGHT_PER_WORKER`` frames at a time: the driver keeps only
    the frames not handed out yet and the few in flight. (Ray Data's streaming executor keeps a few
    kilobytes per finished block until the run ends: the driver's memory then grows with the number
    of frames; ``docs/scaling.md``.) A worker that dies is restarted by Ray (``max_restarts``) and
    its frames are computed again (``max_task_retries``: deaths only, ``FRAME_ATTEMPTS``); a frame
    that raises fails the run.
    """
    workers = min(connect_ray(execution), len(todo))
    import ray
    from ray.exceptions import RayActorError

    worker_class = ray.remote(
        num_cpus=execution.threads,
        max_restarts=-1,
        # Not 0: Ray then fails at once the frames handed to a worker while it restarts.
        max_task_retries=FRAME_ATTEMPTS - 1,
        scheduling_strategy="SPREAD",  # one per node first, on a cluster
    )(_RayWorker)

    def rows() -> Iterator[dict[str, Any]]:
        actors = [worker_class.remote(job, str(out_dir), execution.threads) for _ in range(workers)]
        waiting = collections.deque(todo)
        in_flight: dict[Any, tuple[int, int]] = {}  # result reference -> (actor, frame)
        # Per actor, its references in the order handed out, the order it computes them in.
        queues: list[collections.deque] = [collections.deque() for _ in actors]

        def hand_out(actor: int) -> None:
            if waiting:
                frame = waiting.popleft()
                reference = actors[actor].run.remote(frame)
                in_flight[reference] = (actor, frame)
                queues[actor].append(reference)

        def lost(actor: int, error: RayActorError) -> Exception:
            """The error that ends the run when Ray gave up on one of ``actor``'s frames."""
            if error.actor_init_failed:  # e.g. the job does not unpickle on that node
                return InputError(f"a Ray worker could not start: {' '.join(str(error).split())[:400]}")
            # Every frame the worker held was retried with it; the one it died on is the first
            # of them, in its order, that came back lost (those before it may have finished).
            culprit = in_flight[queues[actor][0]][1]
            for reference in queues[actor]:
                try:
                    ray.get(reference, timeout=10)
                except RayActorError:
                    culprit = in_flight[reference][1]
                    break
                except Exception:  # noqa: BLE001 - finished or still pending: not this one
                    continue
            return FrameLostError(
                f"frame {culprit}: its Ray worker died {FRAME_ATTEMPTS} times while computing it (out of "
                f"memory, or a crash in native code); the frames done so far are kept in {out_dir} "
                "and a re-run resumes"
            )

        try:
            for _ in range(IN_FLIGHT_PER_WORKER):
                for actor in range(workers):
                    hand_out(actor)
            while in_flight:
                (ready,), _ = ray.wait(list(in_flight), num_returns=1)
                actor = in_flight[ready][0]
                try:
                    row = ray.get(ready)
                except RayActorError as exc:
                    raise lost(actor, exc) from exc
                del in_flight[ready]
                queues[actor].remove(ready)
                hand_out(actor)
                yield row
        finally:
            # Done, failed or cancelled (a progress callback that raised): no worker goes on.
            for actor in actors:
                ray.kill(actor, no_restart=True)

    return rows(), workers
