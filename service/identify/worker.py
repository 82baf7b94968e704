"""Identification jobs in a separate process, so the API and the acquisition never stall.

One ``concurrent.futures.ProcessPoolExecutor`` with ``max_workers=1`` and a ``spawn`` context (no forked copy
of the event loop, sockets or database connections). Its initializer loads the model once per worker process
from the reduced-model cache (``service.modelload.load_model``); a job carries only the resampled window
(``service.identify.window.WindowArrays``), the initial field, the warm start and the options.

Cancellation: a shared integer holds the id of the job to cancel; every batch evaluation of the reduced
model checks it (``CancellableModel``) and stops the run. A job that does not stop in time (or exceeds
its timeout) has its process terminated and the pool is recreated (the next job pays the model load
again, about a second with a warm cache).

The worker process runs at ``nice`` 10 (``WORKER_NICE``): the API's latency matters more than an
identification finishing a few milliseconds earlier. A worker whose parent died (the service was killed
with SIGKILL) notices within half a second and exits (``watch_parent``), so a kill -9 leaves neither the
worker nor multiprocessing's resource tracker behind.

Errors::

    WorkerError(RuntimeError)           the pool is closed
    (a failed job is not an exception: it is a JobOutcome whose status is a service.contracts.outcome.Outcome,
    mapped from the job's exception in one place, ``job_outcome_of``)
"""

from __future__ import annotations

import asyncio
import concurrent.futures as cf
import contextlib
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Protocol

import numpy as np
import numpy.typing as npt

from service.contracts.outcome import Outcome
from service.errors import ServiceError
from service.estimate.live import LiveStateError
from service.identify.window import InsufficientWindowError, WindowArrays
from service.modelload import LoadedModel, ModelRef, load_model

if TYPE_CHECKING:
    from model.hmap_identify import MapFit
    from model.identify import IdentificationResult, Window
    from model.identify_prior import HPrior
    from model.rom import InputLike, ReducedModel
    from service.identify.mapjob import MapJob

__all__ = [
    "IdentificationWorker",
    "JobOutcome",
    "JobRequest",
    "JobStatus",
    "WorkerError",
    "job_outcome_of",
    "run_job",
    "run_job_in_process",
    "supervise_job",
    "terminate_pool",
]


class WorkerError(ServiceError, RuntimeError):
    """The worker cannot take jobs (closed)."""


# A job's status is the outcome that is stored: OK, FAILED, CANCELLED or INSUFFICIENT_DATA (never SKIPPED).
JobStatus = Outcome


@dataclass(frozen=True, eq=False, kw_only=True)
class JobRequest:
    job_id: int
    window: WindowArrays
    t0_c: float | np.ndarray  # uniform °C or (N,) initial field at window.times_s[0]
    warm_start: tuple[float, ...] | None
    # from the core's configuration (experimental.method, seed, ...; no defaults here)
    method: str
    seed: int
    estimate_loads: bool
    estimate_t0_shift: bool = False  # fit a uniform offset of t0_c too
    carry_start_error: bool  # CIs carry the start field's error (start_cov)
    # (r, r) °C² covariance of t0_c's error in reduced coordinates: the filtered live state's at the window
    # start (None: exact)
    start_cov: np.ndarray | None = None
    start_modes: int  # fit the start's leading uncertain directions too (IdentifyOptions.start_modes)
    time_budget_s: float | None
    ci_threshold: float  # 95 % half-width of log H above which an H is not identified
    offsets_c: np.ndarray | None = None  # (32,) °C sensor offsets to subtract (service.acquire.calibration)
    offset_sd_c: np.ndarray | None = None  # (32,) °C 1σ of the offsets still unknown, carried in the CIs
    # speed-map mode (docs/design/hmap.md): fit H = F(n, Ti) with this prior instead of one H for the window
    speed_map: MapJob | None = None
    # served modes' per-condition fits: a Gaussian prior on ln H, a MAP fit (service.identify.prior;
    # None: the paper's unregularised fit)
    prior: HPrior | None = None


@dataclass(frozen=True, eq=False, kw_only=True)
class JobOutcome:
    job_id: int
    status: Outcome
    message: str
    wall_s: float = 0.0
    result: IdentificationResult | None = None  # when OK
    final_field_c: np.ndarray | None = None  # (N,) fitted model's field at the window end, °C (when OK)
    map_fit: MapFit | None = None  # speed-map jobs: the fit (posterior, visited speeds; when OK)


# --- inside the worker process --------------------------------------------------------------------
_MODEL: LoadedModel | None = None


class CancelFlag(Protocol):
    """A shared ``multiprocessing.Value("q")``: the id of the job to cancel, -1 for none."""

    value: int


_CANCEL: CancelFlag | None = None


class JobCancelled(ServiceError):
    """Raised inside the worker process when the running job was cancelled."""


def _init_worker(ref: ModelRef, cancel: CancelFlag, parent_pid: int | None = None, nice: int = 0) -> None:
    global _MODEL, _CANCEL
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle (it closes the pool)
    if parent_pid is not None:
        watch_parent(parent_pid)
    if nice > 0:
        with contextlib.suppress(OSError):  # lowering one's own priority needs no privilege; be safe anyway
            os.nice(nice)
    _CANCEL = cancel
    _MODEL = load_model(ref)


def watch_parent(
    parent_pid: int, *, poll_s: float = 0.5, exit: Callable[[int], object] = os._exit
) -> threading.Thread:
    """Exit this process when ``parent_pid`` is gone (a daemon thread polls ``os.getppid()``).

    A service killed with SIGKILL runs no clean-up, and the pool's worker would wait for jobs for ever (it
    holds both ends of its call queue, so it never sees EOF), keeping multiprocessing's resource tracker alive
    too. When the parent dies the worker is re-parented (to init or a subreaper), so ``getppid()`` changes.
    """

    def run() -> None:
        while os.getppid() == parent_pid:
            time.sleep(poll_s)
        exit(0)

    thread = threading.Thread(target=run, name="chtc-watch-parent", daemon=True)
    thread.start()
    return thread


def _ping() -> str:
    assert _MODEL is not None
    return _MODEL.version


def to_model_window(model: LoadedModel, window: WindowArrays, t0_c: float | np.ndarray) -> Window:
    """``model.identify.Window`` from the resampled arrays (bearing heat from speed and torque)."""
    from model.identify import Window
    from model.inputs import inputs_from_operation

    ambient, speed, torque = window.step_inputs()
    inputs = inputs_from_operation(
        model.spec, dt_s=window.dt_s, speed_rpm=speed, torque_nm=torque, ambient_c=ambient
    )
    return Window(
        inputs=inputs,
        measured_c=window.measured_c,
        mask=window.mask,
        t0=t0_c,
        speed_rpm=float(np.mean(speed)),
    )


class CancellableModel:
    """The reduced model seen by the optimizer: every batch evaluation first checks the cancel flag.

    ``model.identify.identify`` has no callback, but it evaluates the model many times per second, so this is
    where a cancelled job stops (within one batch, milliseconds).
    """

    def __init__(self, rom: ReducedModel, should_stop: Callable[[], bool]) -> None:
        self._rom = rom
        self._should_stop = should_stop

    def simulate_sensors(
        self,
        h: npt.NDArray[np.float64],
        inputs: InputLike,
        t0: float | npt.NDArray[np.float64],
        *,
        load_scale: npt.NDArray[np.float64] | None = None,
        t0_shift: npt.NDArray[np.float64] | None = None,
    ) -> npt.NDArray[np.float64]:
        if self._should_stop():
            raise JobCancelled
        return self._rom.simulate_sensors(h, inputs, t0, load_scale=load_scale, t0_shift=t0_shift)

    def __getattr__(self, name: str) -> object:  # a proxy: everything else is the ReducedModel's
        return getattr(self._rom, name)


def run_identification(
    model: LoadedModel, req: JobRequest, *, should_stop: Callable[[], bool] | None = None
) -> tuple[IdentificationResult, Window]:
    """``model.identify.identify`` for one request -> (result, model window); the rng is seeded from it."""
    from model.identify import IdentifyOptions, identify

    rom = model.rom if should_stop is None else CancellableModel(model.rom, should_stop)
    window = to_model_window(model, req.window, req.t0_c)
    result = identify(
        rom,
        window,
        method=req.method,
        box=model.ref.h_box,
        rng=np.random.default_rng(req.seed),
        warm_start=None if req.warm_start is None else np.asarray(req.warm_start, dtype=float),
        estimate_loads=req.estimate_loads,
        estimate_t0_shift=req.estimate_t0_shift,
        offsets_c=req.offsets_c,
        offset_sd_c=req.offset_sd_c,
        start_cov=start_covariance(model, req) if req.carry_start_error else None,
        spec=model.spec,
        options=IdentifyOptions(
            time_budget_s=req.time_budget_s, ci_threshold=req.ci_threshold, start_modes=req.start_modes
        ),
        prior=req.prior,
    )
    return result, window


def start_covariance(model: LoadedModel, req: JobRequest) -> np.ndarray:
    """The error covariance (r, r) [°C², reduced] of the window's start field (the filtered live state's),
    zeros when it has none."""
    if req.start_cov is None:
        return np.zeros((model.rom.rank, model.rom.rank))
    return np.asarray(req.start_cov, dtype=np.float64)


def final_field(model: LoadedModel, window: Window, result: IdentificationResult) -> np.ndarray:
    """The reduced model's field (N,) °C at the end of the window with the identified H (and load scales),
    from the window's start field plus the fitted uniform shift (if any)."""
    ens = result.end_ensemble
    if ens is not None:  # the identification already ran the window with these parameters
        return np.asarray(model.rom.lift(ens.a_end))
    ls = result.load_scale
    shift = result.t0_shift_c
    traj = model.rom.simulate_state(
        np.asarray(result.h, dtype=float),
        window.inputs,
        window.t0 if shift is None else np.asarray(window.t0, dtype=float) + float(shift),
        load_scale=None if ls is None else np.asarray(ls, dtype=float),
    )
    return np.asarray(model.rom.lift(traj[-1]))


def job_outcome_of(err: Exception) -> tuple[Outcome, str]:
    """The stored outcome and message of a job that raised ``err`` (the one mapping): too few usable data,
    found by the window rules, the live state (no start field that old) or the identification itself, is
    INSUFFICIENT_DATA with its reason; a cancelled job CANCELLED; anything else FAILED, naming the error
    class."""
    from model.identify import InsufficientDataError  # the service process imports no optimizer

    if isinstance(err, JobCancelled):
        return Outcome.CANCELLED, "cancelled"
    if isinstance(err, InsufficientWindowError):
        return Outcome.INSUFFICIENT_DATA, err.reason
    if isinstance(err, InsufficientDataError | LiveStateError):
        return Outcome.INSUFFICIENT_DATA, str(err)
    return Outcome.FAILED, f"{type(err).__name__}: {err}"


def run_job(
    model: LoadedModel | None, req: JobRequest, *, should_stop: Callable[[], bool] | None = None
) -> JobOutcome:
    """Run one job; never raises: every failure becomes an outcome (``job_outcome_of``). Wall time in s."""
    started = time.perf_counter()
    try:
        if model is None:
            raise RuntimeError("worker process has no model (initializer failed)")
        if req.speed_map is not None:
            done = _run_map_job(model, req)
        else:
            result, window = run_identification(model, req, should_stop=should_stop)
            done = JobOutcome(
                job_id=req.job_id,
                status=Outcome.OK,
                message=result.message,
                result=result,
                final_field_c=final_field(model, window, result),
            )
    except Exception as err:  # the boundary of a job: report, never crash the pool or the offline run
        status, msg = job_outcome_of(err)
        done = JobOutcome(job_id=req.job_id, status=status, message=msg)
    return replace(done, wall_s=time.perf_counter() - started)


def _run_map_job(model: LoadedModel, req: JobRequest) -> JobOutcome:
    """A speed-map job (``service.identify.mapjob``). Not cancellable: it runs ~0.1-1 s and the next window
    starts from its posterior (docs/design/hmap.md)."""
    from service.identify.mapjob import run_map_identification

    assert req.speed_map is not None
    fit = run_map_identification(
        model,
        req.window,
        req.t0_c,
        req.speed_map,
        req.offsets_c,
        req.offset_sd_c,
        start_cov=req.start_cov,
        start_modes=req.start_modes,
    )
    return JobOutcome(
        job_id=req.job_id,
        status=Outcome.OK,
        message=fit.message,
        final_field_c=fit.end_field_c,
        map_fit=fit,
    )


def run_job_in_process(req: JobRequest) -> JobOutcome:
    """The function the pool runs: ``run_job`` on the process's model, stopping when the job is cancelled."""

    def should_stop() -> bool:
        return _CANCEL is not None and _CANCEL.value == req.job_id

    return run_job(_MODEL, req, should_stop=should_stop)


# --- in the service process -----------------------------------------------------------------------
def terminate_pool(pool: cf.ProcessPoolExecutor, *, wait: bool) -> None:
    """Terminate the pool's processes and shut it down: ``ProcessPoolExecutor`` has no public terminate, and
    a stuck job has to be killed to free its process."""
    for proc in list(getattr(pool, "_processes", {}).values()):
        proc.terminate()
    pool.shutdown(wait=wait, cancel_futures=True)


# The worker runs at a lower priority so that an identification (a whole core for up to a second) does not
# push the API's /chtc p99 above twice its idle value on a 2-core machine (docs/design/api.md).
WORKER_NICE = 10
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@contextlib.contextmanager
def single_threaded_children() -> Iterator[None]:
    """Environment for a spawned worker: one BLAS thread, so it leaves a core to the event loop; SIGINT
    ignored from its first instruction (a child inherits an ignored signal, and Python then installs no
    ``KeyboardInterrupt`` handler), so a Ctrl-C in the terminal, which reaches the whole process group, is
    left to the parent instead of printing the worker's traceback."""
    saved = {k: os.environ.get(k) for k in _THREAD_VARS}
    os.environ.update(dict.fromkeys(_THREAD_VARS, "1"))
    main_thread = threading.current_thread() is threading.main_thread()
    sigint = signal.getsignal(signal.SIGINT) if main_thread else None  # None: not ours to change back
    if sigint is not None:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        if sigint is not None:
            signal.signal(signal.SIGINT, sigint)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


async def supervise_job(
    submit: Callable[[], asyncio.Future[JobOutcome]],
    job_id: int,
    *,
    timeout_s: float,
    cancel_grace_s: float,
    cancel: Callable[[], None],
    discard: Callable[[], None],
) -> JobOutcome:
    """One job's life in a process pool, the one copy that ``IdentificationWorker`` and
    ``service.identify.pool.WorkerPool`` both run.

    ``submit()`` hands the job to the pool (in ``single_threaded_children``: a recreated pool spawns its
    process on this submit). Past ``timeout_s`` the job is asked to stop (``cancel()``) and ends as FAILED; a
    cancelled caller asks it to stop too and the ``CancelledError`` goes on. A job that does not stop within
    ``cancel_grace_s`` after either has its pool's processes terminated (``discard()``), as has a broken pool,
    whose job ends as FAILED "worker process died".
    """
    started = time.perf_counter()
    try:
        with single_threaded_children():
            fut = submit()
        # a job given up (cancelled, discarded) may still end in an error nobody awaits: the pool's close
        # terminates its process (BrokenProcessPool); asyncio then logged "Future exception was never
        # retrieved" at every stop during a job (issue 41)
        fut.add_done_callback(_retrieve)
        try:
            return await asyncio.wait_for(asyncio.shield(fut), timeout=timeout_s)
        except TimeoutError:
            cancel()
            msg = f"identification exceeded timeout_s={timeout_s:.0f} s"
            return await _after_cancel(fut, job_id, msg, started, Outcome.FAILED, cancel_grace_s, discard)
        except asyncio.CancelledError:
            cancel()
            await _after_cancel(fut, job_id, "cancelled", started, Outcome.CANCELLED, cancel_grace_s, discard)
            raise
    except BrokenProcessPool as err:
        discard()
        return JobOutcome(job_id=job_id, status=Outcome.FAILED, message=f"worker process died: {err}")


def _retrieve(fut: asyncio.Future[JobOutcome]) -> None:
    if not fut.cancelled():
        fut.exception()


async def _after_cancel(
    fut: asyncio.Future[JobOutcome],
    job_id: int,
    message: str,
    started: float,
    status: Outcome,
    grace_s: float,
    discard: Callable[[], None],
) -> JobOutcome:
    """Wait ``grace_s`` for a job asked to stop; one that does not (or whose pool broke) is discarded."""
    try:
        await asyncio.wait_for(asyncio.shield(fut), timeout=grace_s)
    except (TimeoutError, BrokenProcessPool):
        discard()
    return JobOutcome(job_id=job_id, status=status, message=message, wall_s=time.perf_counter() - started)


class IdentificationWorker:
    """Async façade over a one-process pool; ``await run(req)`` returns a :class:`JobOutcome`."""

    def __init__(
        self,
        ref: ModelRef,
        *,
        context: str = "spawn",
        timeout_s: float = 120.0,
        cancel_grace_s: float = 5.0,
        nice: int = WORKER_NICE,
    ) -> None:
        self.ref = ref
        self.nice = nice
        self.timeout_s = timeout_s
        self.cancel_grace_s = cancel_grace_s
        self._ctx = multiprocessing.get_context(context)
        self._cancel: CancelFlag = self._ctx.Value("q", -1)
        self._pool: cf.ProcessPoolExecutor | None = None
        self._closed = False
        self.running_job: int | None = None
        self.restarts = 0
        self.model_version: str | None = None

    def _ensure_pool(self) -> cf.ProcessPoolExecutor:
        if self._closed:
            raise WorkerError("the identification worker is closed")
        if self._pool is None:
            self._pool = cf.ProcessPoolExecutor(
                max_workers=1,
                mp_context=self._ctx,
                initializer=_init_worker,
                initargs=(self.ref, self._cancel, os.getpid(), self.nice),
            )
        return self._pool

    async def start(self) -> str:
        """Start the process and load the model there; returns the model version (waits for it)."""
        loop = asyncio.get_running_loop()
        with single_threaded_children():  # the process is spawned by this first submit
            fut = loop.run_in_executor(self._ensure_pool(), _ping)
        self.model_version = await fut
        return self.model_version

    async def run(self, req: JobRequest) -> JobOutcome:
        loop = asyncio.get_running_loop()
        self.running_job = req.job_id  # the cancel flag is not reset: job ids are unique
        try:
            return await supervise_job(
                lambda: loop.run_in_executor(self._ensure_pool(), run_job_in_process, req),
                req.job_id,
                timeout_s=self.timeout_s,
                cancel_grace_s=self.cancel_grace_s,
                cancel=lambda: self.cancel(req.job_id),
                discard=self._discard_pool,
            )
        finally:
            self.running_job = None

    def pids(self) -> list[int]:
        """Process ids of the live worker processes (none before ``start()`` or after ``close()``)."""
        pool = self._pool
        procs = getattr(pool, "_processes", None) or {}
        return [p.pid for p in list(procs.values()) if p.pid is not None and p.is_alive()]

    def cancel(self, job_id: int) -> None:
        """Ask the running job ``job_id`` to stop at its next reduced-model evaluation."""
        self._cancel.value = job_id

    def _discard_pool(self) -> None:
        pool, self._pool = self._pool, None
        if pool is None:
            return
        self.restarts += 1
        terminate_pool(pool, wait=False)

    def close(self) -> None:
        self._closed = True
        pool, self._pool = self._pool, None
        if pool is not None:
            terminate_pool(pool, wait=True)
