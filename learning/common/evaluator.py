"""Evaluators: run a function over a list of jobs, locally in a process pool or on a Ray cluster.

Training by evolution (`felis.learning.landing.train`) spends its time in rollouts, each a deterministic
function of its job (an individual and an orientation). An `Evaluator` maps such a function over a list of
jobs and returns the results **in job order**; which evaluator ran them never changes the numbers, since
all randomness is drawn in the parent process and each worker only runs deterministic rollouts.

- `ProcessPoolEvaluator`: a local process pool (default: every core), created on the first `map` and kept
  until `close`, so a per-worker object built by ``initializer(*initargs)`` (a compiled simulation, stored
  in a module-level global of the job function's module, as `felis.learning.landing.evaluate` does) serves
  every generation. ``workers=1`` runs the jobs inline in this process (``initializer`` runs here once).
- `RayEvaluator`: the same on Ray (``pip install felis[cluster]``): ``address="local"`` starts a local Ray
  with ``num_cpus``; any other address joins that cluster (``"auto"``, ``"ray://host:10001"``). Jobs go out
  in batches, one remote task per batch; each Ray worker process runs ``initializer(*initargs)`` once per
  evaluator (tracked by a token) before its first batch, and keeps the result for later batches.

Every evaluator runs its jobs with the numeric libraries' thread pools (BLAS, OpenMP) limited to one thread
(`threadpoolctl`, where installed): the processes are the parallelism, and oversubscribed BLAS threads
made a 2-process pool a third slower; it also gives every evaluator the same single-threaded arithmetic.

Jobs travel in batches of ``chunksize`` (default: about four batches per worker per `map`), so the
per-task overhead (pickling, scheduling) is paid per batch rather than per rollout.

`make_evaluator` picks one from the command line's ``--ray ADDRESS`` / ``--workers N``.

**Stopping** (`worker_pool`, `kill_pool`): a pool worker ignores Ctrl-C and dies of SIGTERM and SIGHUP; the
parent, whose `felis.shutdown` turns the signal into `Interrupted`, kills its workers at once and lets the
exception go on, so a stopped command ends in well under a second with what its checkpoints hold, never waiting
for a search in a worker to finish. (Workers forked inside `felis.shutdown.signals` used to inherit its handler,
which ignores every signal after the first: a pool torn down after a SIGTERM to the process group waited for
ever on workers that ignored its own SIGTERM.)
"""

from __future__ import annotations

import math
import os
import signal
import sys
import uuid
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Protocol, runtime_checkable

from felis.errors import EvaluatorError, ParameterError

BATCHES_PER_WORKER = 4  # default chunking: about this many batches per worker in one map call


def worker_count(workers: int | None, n_jobs: int) -> int:
    """The processes for ``n_jobs`` jobs: ``workers`` (default every core), at most one per job, at least 1."""
    return max(1, min(workers or os.cpu_count() or 1, n_jobs))


def _worker_signals(initializer: Callable[..., None] | None, initargs: tuple) -> None:
    """A pool worker's first act (module doc, Stopping), then the caller's ``initializer``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    for s in (signal.SIGTERM, getattr(signal, "SIGHUP", None)):
        if s is not None:
            signal.signal(s, signal.SIG_DFL)
    if initializer is not None:
        initializer(*initargs)


def worker_pool(workers: int, initializer: Callable[..., None] | None = None,
                initargs: tuple = ()) -> ProcessPoolExecutor:
    """A process pool whose workers leave stopping to this process (module doc, Stopping)."""
    return ProcessPoolExecutor(workers, initializer=_worker_signals, initargs=(initializer, tuple(initargs)))


def kill_pool(pool: ProcessPoolExecutor) -> None:
    """End ``pool`` now: its workers killed (they hold nothing a checkpoint needs: the parent writes those),
    queued jobs cancelled, no wait for running ones."""
    for p in list((getattr(pool, "_processes", None) or {}).values()):
        p.kill()
    pool.shutdown(wait=False, cancel_futures=True)


def run_jobs(fn: Callable[[Any], Any], jobs: Sequence, workers: int, initializer: Callable[..., None] | None = None,
             initargs: tuple = (), chunksize: int = 4, progress: Callable[[int], None] | None = None) -> list:
    """``fn`` over ``jobs``, results in job order: inline when ``workers`` is 1 (``initializer(*initargs)``
    first, here), else in a process pool of ``workers`` made for this call (each process runs the
    initializer), jobs in batches of ``chunksize``; ``progress(1)`` after each result. Unlike the
    evaluators, the numeric libraries' thread pools are left as they are."""
    out = []
    if workers == 1:
        if initializer is not None:
            initializer(*initargs)
        for job in jobs:
            out.append(fn(job))
            if progress:
                progress(1)
        return out
    pool = worker_pool(workers, initializer, initargs)
    try:
        for result in pool.map(fn, jobs, chunksize=chunksize):
            out.append(result)
            if progress:
                progress(1)
    except BaseException:  # Ctrl-C, SIGTERM, a job's error: nothing more is wanted from the workers
        kill_pool(pool)
        raise
    pool.shutdown(wait=True)
    return out


@runtime_checkable
class Evaluator(Protocol):
    """Maps a picklable, module-level function over jobs; results in job order."""

    def map(self, fn: Callable[[Any], Any], jobs: list) -> list: ...

    def close(self) -> None: ...

    def describe(self) -> str: ...


def single_threaded():
    """Limit BLAS/OpenMP thread pools to one thread in this process (module doc); returns the
    `threadpoolctl` limiter (a context manager that restores the old limits) or None without it."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # scikit-learn's dependency; without it the libraries keep their defaults
        return None
    return threadpool_limits(limits=1)


def _pool_init(initializer: Callable[..., None] | None, initargs: tuple) -> None:
    """Initializer of an evaluator's worker process: single-threaded libraries, then the caller's initializer."""
    single_threaded()
    if initializer is not None:
        initializer(*initargs)


def _chunk(n_jobs: int, workers: int, chunksize: int | None) -> int:
    if chunksize is not None:
        return chunksize
    return max(1, math.ceil(n_jobs / (BATCHES_PER_WORKER * max(1, workers))))


def _check_chunksize(chunksize: int | None) -> None:
    if chunksize is not None and (isinstance(chunksize, bool) or not isinstance(chunksize, int) or chunksize < 1):
        raise ParameterError(f"chunksize must be a positive integer, got {chunksize!r}")


class ProcessPoolEvaluator:
    """A local process pool (module doc).

    Args:
        workers: processes; None = every core (``os.cpu_count()``); 1 = inline, no subprocess.
        initializer, initargs: run once per worker process (inline: once, here) before its first job.
        chunksize: jobs per batch sent to a worker; None = about `BATCHES_PER_WORKER` batches per worker.
    """

    def __init__(self, workers: int | None = None, initializer: Callable[..., None] | None = None,
                 initargs: Sequence[Any] = (), chunksize: int | None = None):
        if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
            raise ParameterError(f"workers must be a positive integer, got {workers!r}")
        _check_chunksize(chunksize)
        self.workers = workers or os.cpu_count() or 1
        self.initializer, self.initargs, self.chunksize = initializer, tuple(initargs), chunksize
        self._pool: ProcessPoolExecutor | None = None
        self._initialised = False  # inline mode

    def map(self, fn: Callable[[Any], Any], jobs: list) -> list:
        jobs = list(jobs)
        if not jobs:
            return []
        if self.workers == 1:
            limiter = single_threaded()  # restored after the map: this is the caller's process
            try:
                if not self._initialised and self.initializer is not None:
                    self.initializer(*self.initargs)
                self._initialised = True
                return [fn(j) for j in jobs]
            finally:
                if limiter is not None:
                    limiter.restore_original_limits()
        if self._pool is None:
            self._pool = worker_pool(self.workers, _pool_init, (self.initializer, self.initargs))
        try:
            return list(self._pool.map(fn, jobs, chunksize=_chunk(len(jobs), self.workers, self.chunksize)))
        except BrokenProcessPool:
            self._pool = None
            raise EvaluatorError(f"a worker process of the {self.workers}-process pool died (out of memory or a "
                                 "crash); rerun with fewer workers, or resume from the last checkpoint") from None
        except BaseException:  # Ctrl-C, SIGTERM, a job's error: stop the workers now (module doc, Stopping)
            pool, self._pool = self._pool, None
            kill_pool(pool)
            raise

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def __enter__(self) -> ProcessPoolEvaluator:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def describe(self) -> str:
        return "inline (1 process)" if self.workers == 1 else f"process pool ({self.workers} workers)"


# ------------------------------------------------------------------------------------------------ Ray
_RAY_TOKEN: str | None = None  # per Ray worker process: the evaluator whose initializer ran here last


def _ray_batch(token: str, initializer: Callable[..., None] | None, initargs: tuple, fn: Callable[[Any], Any],
               batch: list) -> list:
    """Body of the remote task: (re)initialise this worker for the evaluator ``token``, then run a batch."""
    global _RAY_TOKEN
    if _RAY_TOKEN != token:
        single_threaded()
        if initializer is not None:
            initializer(*initargs)
        _RAY_TOKEN = token
    return [fn(j) for j in batch]


def _ray_initialized() -> bool:
    ray = sys.modules.get("ray")
    return bool(ray is not None and getattr(ray, "is_initialized", lambda: False)())


def _import_ray():
    try:
        import ray
    except ImportError:
        raise ParameterError("Ray is not installed: install felis[cluster] (pip install 'felis[cluster]') to "
                             "evaluate on a Ray cluster, or leave out the Ray address to use local processes"
                             ) from None
    return ray


#: Ray's own switch for a single-machine Ray (how it runs on macOS and Windows): the node is reached as
#: 127.0.0.1, so the GCS, the raylet and the workers listen on the loopback address only.
RAY_LOCAL_ONLY_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


def local_ray_options(num_cpus: int | None) -> dict:
    """``ray.init`` keywords for a local Ray bound to the loopback address.

    ``_node_ip_address="127.0.0.1"`` alone is not enough on Linux: Ray 2.60 resolves a loopback node
    address to the machine's network address and its servers then listen on every interface (measured
    with ``ss -ltn``: ``*:port``). With `RAY_LOCAL_ONLY_ENV` = 0 (`prefer_loopback_ray`, called before
    Ray is imported or started), Ray keeps 127.0.0.1 and every listening socket is on it. The dashboard
    is off.
    """
    return {"num_cpus": num_cpus, "include_dashboard": False, "dashboard_host": "127.0.0.1",
            "_node_ip_address": "127.0.0.1", "log_to_driver": False}


def prefer_loopback_ray() -> None:
    """Make a Ray started from this process a single-machine Ray on 127.0.0.1 (see `local_ray_options`).

    Ray reads `RAY_LOCAL_ONLY_ENV` once, when it is imported; the variable is set for Ray's child
    processes, and where Ray was imported before this call its module constant is set to match."""
    os.environ[RAY_LOCAL_ONLY_ENV] = "0"
    constants = sys.modules.get("ray._private.ray_constants")
    if constants is not None and getattr(constants, "ENABLE_RAY_CLUSTER", False):
        constants.ENABLE_RAY_CLUSTER = False


class RayEvaluator:
    """Jobs on Ray (module doc).

    Args:
        address: ``"local"`` starts a local Ray with ``num_cpus`` CPUs (None: every core); anything else is
            passed to ``ray.init(address=...)`` (e.g. ``"auto"``, ``"ray://head:10001"``). If Ray is already
            initialised in this process, that session is used and left running on `close`.
        num_cpus: local Ray only.
        initializer, initargs: run once per Ray worker process before its first batch for this evaluator.
        chunksize: jobs per remote task; None = about `BATCHES_PER_WORKER` tasks per cluster CPU.
    """

    def __init__(self, address: str, num_cpus: int | None = None, initializer: Callable[..., None] | None = None,
                 initargs: Sequence[Any] = (), chunksize: int | None = None):
        if not isinstance(address, str) or not address.strip():
            raise ParameterError(f"Ray address must be 'local' or a cluster address, got {address!r}")
        if num_cpus is not None and (isinstance(num_cpus, bool) or not isinstance(num_cpus, int) or num_cpus < 1):
            raise ParameterError(f"num_cpus must be a positive integer, got {num_cpus!r}")
        if num_cpus is not None and address != "local":
            raise ParameterError("num_cpus applies to a local Ray only (address 'local'); a cluster has its own")
        _check_chunksize(chunksize)
        if address == "local" and not _ray_initialized():
            prefer_loopback_ray()  # before Ray is imported where it can be
        ray = _import_ray()
        self._ray, self.address, self.chunksize = ray, address, chunksize
        self._owns = not ray.is_initialized()
        if self._owns:
            try:
                if address == "local":
                    ray.init(**local_ray_options(num_cpus))
                else:
                    ray.init(address=address, log_to_driver=False)
            except (ConnectionError, RuntimeError, ValueError) as e:
                raise ParameterError(f"cannot connect to Ray at {address!r}: {' '.join(str(e).split())[:200]}"
                                     ) from None
        self._cpus = 1
        self._token = uuid.uuid4().hex  # identifies this evaluator's initializer on the workers
        self._initargs_ref = ray.put((initializer, tuple(initargs)))
        self._remote = ray.remote(_ray_remote_entry)

    @property
    def workers(self) -> int:
        """CPUs in the cluster now (the last known count once closed)."""
        if self._ray.is_initialized():
            self._cpus = max(1, int(self._ray.cluster_resources().get("CPU", 1)))
        return self._cpus

    def map(self, fn: Callable[[Any], Any], jobs: list) -> list:
        jobs = list(jobs)
        if not jobs:
            return []
        size = _chunk(len(jobs), self.workers, self.chunksize)
        refs = [self._remote.remote(self._token, self._initargs_ref, fn, jobs[i:i + size])
                for i in range(0, len(jobs), size)]
        out: list = []
        for batch in self._ray.get(refs):
            out.extend(batch)
        return out

    def close(self) -> None:
        if self._owns and self._ray.is_initialized():
            self._ray.shutdown()
        self._owns = False

    def __enter__(self) -> RayEvaluator:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def describe(self) -> str:
        return f"Ray at {self.address} ({self.workers} CPUs)"


def _ray_remote_entry(token: str, init: tuple, fn: Callable[[Any], Any], batch: list) -> list:
    """The function Ray runs remotely (``init``: the (initializer, initargs) pair, from the object store)."""
    initializer, initargs = init
    return _ray_batch(token, initializer, initargs, fn, batch)


def make_evaluator(ray_address: str | None = None, workers: int | None = None,
                   initializer: Callable[..., None] | None = None, initargs: Sequence[Any] = (),
                   chunksize: int | None = None) -> ProcessPoolEvaluator | RayEvaluator:
    """`RayEvaluator` when ``ray_address`` is given (``workers`` is then the local Ray's CPU count, for
    ``"local"`` only), else `ProcessPoolEvaluator` with ``workers`` processes (None: every core)."""
    if ray_address:
        return RayEvaluator(ray_address, num_cpus=workers if ray_address == "local" else None,
                            initializer=initializer, initargs=initargs, chunksize=chunksize)
    return ProcessPoolEvaluator(workers, initializer=initializer, initargs=initargs, chunksize=chunksize)
