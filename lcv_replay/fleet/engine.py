"""The Ray side of fleet runs: one cluster connection and one scheduling loop, shared by ``batch``
and ``bench suite --workers``.

* **Cluster.** Without an address, :class:`Cluster` starts an embedded local Ray sized to
  ``workers`` CPUs: no dashboard, every Ray process bound to 127.0.0.1 (Ray's own switch for
  that, ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``), Ray's token authentication on, a small object
  store; it is shut down on exit. With ``address`` (``auto``, ``HOST:PORT`` or ``ray://HOST:PORT``) it
  joins an existing cluster, after a TCP check of the address that fails within
  :data:`CONNECT_TIMEOUT_S` instead of hanging. If the process already holds a Ray connection (a
  test fixture, a notebook), that connection is used and left open.
* **Tasks.** Each job is one Ray task with its CPU needs declared (``num_cpus``) and the thread
  pools inside capped to match (OpenMP, OpenBLAS, MKL, numexpr through the job's environment;
  torch and OpenCV by :func:`cap_threads`), so N tasks on N cores do not oversubscribe. On a
  joined cluster the job also ships this process's ``lcv_replay`` and ``recorders`` packages. A worker
  that dies (SIGKILL, the OOM killer, a segfault) is retried by Ray up to ``max_retries`` times.
  Errors inside a task are the task's business: fleet tasks return them as data.
* **Scheduling.** :meth:`Cluster.run` keeps at most :attr:`Cluster.capacity` tasks in flight
  (so "stop" means "submit no more" and the running count is the true one), reports each result
  as it arrives, stops submitting when the stop token (:class:`lcv_replay.replay.StopToken`) is
  set (the first Ctrl-C), and on ``KeyboardInterrupt`` (the second) cancels the running tasks.
"""

from __future__ import annotations

import collections
import logging
import os
import socket
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Generic, Iterable, Sequence, TypeVar

from lcv_replay.errors import ConfigError, FleetError

logger = logging.getLogger(__name__)

J = TypeVar("J")

#: Seconds allowed for a TCP connection to ``--address`` before it is called unreachable.
CONNECT_TIMEOUT_S = 3.0
#: Object store of the embedded cluster: fleet tasks pass file paths and small records only.
LOCAL_OBJECT_STORE_BYTES = 256 * 1024**2
#: Seconds that cancelled tasks get to stop gracefully (KeyboardInterrupt in the task) before
#: their workers are killed.
CANCEL_GRACE_S = 5.0
#: Seconds between two looks at the cluster's CPUs (an autoscaling cluster grows).
CAPACITY_REFRESH_S = 10.0
#: Environment variables that size the thread pools of native libraries in a task.
THREAD_ENV_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS", "VECLIB_MAXIMUM_THREADS")
#: Ray's switch that makes every process of a local cluster listen on 127.0.0.1 only.
_LOOPBACK_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"
_RAY_TEMP_DIR = Path("/tmp/ray")


# --------------------------------------------------------------------------------------- spec
@dataclass(frozen=True)
class ClusterSpec:
    """Where tasks run and how.

    Attributes:
        address: ``None`` for an embedded local cluster; ``"auto"`` (the cluster that ``ray start``
            left on this machine, or ``$RAY_ADDRESS``), ``"HOST:PORT"`` (its GCS) or
            ``"ray://HOST:PORT"`` (Ray Client) to join one.
        workers: tasks at a time. Local: the cluster gets ``workers * cpus_per_task`` CPUs
            (default: this machine's cores over ``cpus_per_task``); joined: at most this many
            (default: as many as the cluster's CPUs allow).
        cpus_per_task: CPUs each task declares, and the threads it may use.
        max_retries: how often Ray re-runs a task whose worker died.
    """

    address: str | None = None
    workers: int | None = None
    cpus_per_task: int = 1
    max_retries: int = 3

    def __post_init__(self) -> None:
        if self.workers is not None and self.workers < 1:
            raise ConfigError(f"--workers {self.workers} is out of range", fix="pass an integer >= 1")
        if self.cpus_per_task < 1:
            raise ConfigError(f"--cpus-per-task {self.cpus_per_task} is out of range", fix="pass an integer >= 1")
        if self.max_retries < 0:
            raise ConfigError(f"--max-retries {self.max_retries} is out of range", fix="pass an integer >= 0")
        if self.address is not None:
            parse_address(self.address)

    @property
    def local(self) -> bool:
        return self.address is None


def parse_address(address: str) -> tuple[str, str | None, int | None]:
    """``(kind, host, port)`` of ``--address``: kind ``auto``, ``gcs`` (``HOST:PORT``) or ``client``
    (``ray://HOST:PORT``).

    Raises:
        ConfigError: anything else.
    """
    if address == "auto":
        return "auto", None, None
    kind, rest = ("client", address[len("ray://"):]) if address.startswith("ray://") else ("gcs", address)
    host, sep, port_text = rest.rpartition(":")
    if not sep or not host or not port_text.isdigit() or not 0 < int(port_text) < 65536:
        raise ConfigError(
            f"--address {address!r} is not a Ray address",
            fix="pass auto, HOST:PORT (the head's GCS port, 6379 by default) or ray://HOST:PORT (Ray Client, 10001 by default)",
        )
    return kind, host.strip("[]"), int(port_text)


def check_reachable(host: str, port: int, *, address: str, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """Raise :class:`FleetError` unless a TCP connection to ``host:port`` opens within ``timeout_s``."""
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            return
    except OSError as exc:
        reason = "timed out" if isinstance(exc, socket.timeout) else (exc.strerror or str(exc))
        raise FleetError(
            f"the Ray cluster at --address {address} is unreachable ({host}:{port}: {reason} within {timeout_s:g} s)",
            fix="start it ('ray start --head' on the head node), check the host and port, or omit --address for a local cluster",
        ) from None


def auto_address() -> str:
    """What ``--address auto`` joins: ``$RAY_ADDRESS``, else the cluster ``ray start`` recorded in
    ``/tmp/ray/ray_current_cluster``.

    Raises:
        FleetError: neither exists.
    """
    from_env = os.environ.get("RAY_ADDRESS", "").strip()
    if from_env and from_env != "auto":
        return from_env
    recorded = _RAY_TEMP_DIR / "ray_current_cluster"
    if recorded.is_file():
        text = recorded.read_text(encoding="utf-8").strip()
        if text:
            return text
    raise FleetError(
        "--address auto: no running Ray cluster found on this machine (no $RAY_ADDRESS, no /tmp/ray/ray_current_cluster)",
        fix="start one with 'ray start --head', pass its address, or omit --address for a local cluster",
    )


def thread_env(cpus: int) -> dict[str, str]:
    """The environment that caps native thread pools to ``cpus`` threads."""
    return {name: str(cpus) for name in THREAD_ENV_VARS}


def cap_threads(cpus: int) -> dict[str, Any]:
    """Cap the thread pools of this process to ``cpus`` (inside a task); returns what was set.

    Environment variables cover libraries not loaded yet; torch and OpenCV are told directly when
    they are already loaded (they read their settings at import otherwise).
    """
    os.environ.update(thread_env(cpus))
    applied: dict[str, Any] = {"cpus": cpus}
    if "torch" in sys.modules:
        torch = sys.modules["torch"]
        torch.set_num_threads(cpus)
        applied["torch_threads"] = torch.get_num_threads()
    if "cv2" in sys.modules:
        sys.modules["cv2"].setNumThreads(cpus)
        applied["cv2_threads"] = cpus
    return applied


# --------------------------------------------------------------------------------------- results
@dataclass(frozen=True)
class TaskResult(Generic[J]):
    """What came back for one job.

    Attributes:
        job: the job as submitted.
        value: the task's return value, or ``None`` when it has none (``failure`` or ``cancelled``).
        failure: one line when Ray could not run the task to its end: the worker died more often
            than ``max_retries``, the node died, the task raised (fleet tasks never do).
        cancelled: the task was cancelled (Ctrl-C twice); it counts as not run.
        seconds: wall time from submission to the result.
    """

    job: J
    value: Any = None
    failure: str | None = None
    cancelled: bool = False
    seconds: float = 0.0


@dataclass(frozen=True)
class RunReport(Generic[J]):
    """The end of :meth:`Cluster.run`: jobs cancelled while running, jobs never submitted, and
    whether the run was aborted (``KeyboardInterrupt``)."""

    cancelled: tuple[J, ...]
    unsubmitted: tuple[J, ...]
    aborted: bool


def first_line(text: str) -> str:
    """The first non-blank line of ``text``, stripped (error messages in one line)."""
    lines = [line.strip() for line in str(text).splitlines() if line.strip()]
    return lines[0] if lines else ""


def describe_failure(exc: BaseException, *, max_retries: int) -> str:
    """One line for a Ray error that ended a task (the task's own errors never get here)."""
    import ray.exceptions as rex

    tries = f"{max_retries + 1} attempt(s)"
    if isinstance(exc, rex.OutOfMemoryError):
        return f"killed by Ray's memory monitor (out of memory) in {tries}; give the task more memory or fewer workers per node"
    if isinstance(exc, rex.WorkerCrashedError):
        return f"the worker process died in each of {tries} (killed, out of memory or crashed); see the Ray worker logs"
    if isinstance(exc, rex.NodeDiedError):
        return f"the node running it died ({first_line(str(exc))})"
    if isinstance(exc, rex.RayTaskError):
        cause = getattr(exc, "cause", None)
        if cause is not None:
            return f"the task raised {type(cause).__name__}: {first_line(str(cause))}"
    return f"{type(exc).__name__}: {first_line(str(exc))}"


# --------------------------------------------------------------------------------------- cluster
class Cluster:
    """A Ray connection for the duration of a ``with`` block (see the module docstring)."""

    def __init__(self, spec: ClusterSpec | None = None):
        self.spec = spec or ClusterSpec()
        self.owned = False
        self.startup_s: float | None = None
        self._capacity: int | None = None
        self._capacity_at = 0.0

    # ------------------------------------------------------------------ connection
    def __enter__(self) -> "Cluster":
        self.connect()
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def connect(self) -> None:
        """Start or join the cluster (see :class:`ClusterSpec`).

        Raises:
            FleetError: the address is unreachable, or Ray fails to start or connect.
        """
        spec = self.spec
        target = None
        if spec.local:
            _bind_local_ray_to_loopback()
        else:
            target = auto_address() if spec.address == "auto" else spec.address
            _, host, port = parse_address(target)
            check_reachable(host, port, address=spec.address)
        started = time.perf_counter()
        import ray

        if ray.is_initialized():
            logger.info("using this process's Ray connection (%s CPUs)", ray.cluster_resources().get("CPU"))
        else:
            try:
                if spec.local:
                    ray.init(
                        address="local", num_cpus=self.local_cpus(), include_dashboard=False, log_to_driver=False,
                        logging_level=logging.WARNING, namespace="lcv-replay", object_store_memory=LOCAL_OBJECT_STORE_BYTES,
                        runtime_env=self.runtime_env(), _system_config={"task_oom_retries": spec.max_retries},
                    )
                else:
                    ray.init(address=target, log_to_driver=False, logging_level=logging.WARNING, namespace="lcv-replay",
                             runtime_env=self.runtime_env())
            except Exception as exc:  # Ray raises ConnectionError, RuntimeError, ValueError, ...
                where = "start a local Ray cluster" if spec.local else f"join the Ray cluster at {spec.address}"
                fix = "see 'ray status' and the Ray logs under /tmp/ray/session_latest/logs"
                if not spec.local and not os.environ.get("RAY_AUTH_MODE"):
                    fix += ("; a cluster with token authentication (Ray's default) needs RAY_AUTH_MODE=token here, "
                            "with its token in ~/.ray/auth_token or $RAY_AUTH_TOKEN")
                raise FleetError(f"could not {where}: {type(exc).__name__}: {first_line(str(exc))}", fix=fix) from None
            self.owned = True
        self.startup_s = time.perf_counter() - started

    def close(self) -> None:
        if self.owned:
            import ray

            ray.shutdown()
            self.owned = False

    # ------------------------------------------------------------------ facts
    def local_cpus(self) -> int:
        """CPUs of the embedded cluster: ``workers * cpus_per_task``, by default the machine's cores."""
        cores = os.cpu_count() or 1
        workers = self.spec.workers or max(cores // self.spec.cpus_per_task, 1)
        return workers * self.spec.cpus_per_task

    def cluster_cpus(self) -> float:
        import ray

        return float(ray.cluster_resources().get("CPU", 0.0))

    @property
    def capacity(self) -> int:
        """Tasks run at once: the cluster's CPUs over ``cpus_per_task`` (at least 1), at most
        ``workers``. Refreshed every :data:`CAPACITY_REFRESH_S`."""
        now = time.monotonic()
        if self._capacity is None or now - self._capacity_at > CAPACITY_REFRESH_S:
            slots = max(int(self.cluster_cpus() // self.spec.cpus_per_task), 1)
            if self.spec.workers is not None:
                slots = min(slots, self.spec.workers)
            self._capacity, self._capacity_at = slots, now
        return self._capacity

    def describe(self) -> dict[str, Any]:
        """For ``run.json``: Ray's version, the address, nodes, CPUs, slots, start-up seconds."""
        import ray

        nodes = [n for n in ray.nodes() if n.get("Alive")]
        return {
            "ray_version": ray.__version__,
            "address": "local" if self.spec.local else self.spec.address,
            "embedded": self.owned and self.spec.local,
            "nodes": len(nodes),
            "cluster_cpus": self.cluster_cpus(),
            "cpus_per_task": self.spec.cpus_per_task,
            "concurrent_tasks": self.capacity,
            "max_retries": self.spec.max_retries,
            "startup_s": self.startup_s,
        }

    # ------------------------------------------------------------------ running
    def runtime_env(self) -> dict[str, Any]:
        """The tasks' environment: thread pools capped to ``cpus_per_task`` (tasks also cap torch
        and OpenCV themselves, :func:`cap_threads`); on a joined cluster, also this process's
        ``lcv_replay`` and ``recorders`` packages (``py_modules``), so the nodes run the driver's
        code whatever version they have installed (they need its dependencies).

        It is set for the whole job when the connection is made (local folders can be shipped only
        then), so the workers the embedded cluster starts with serve the tasks.
        """
        env: dict[str, Any] = {"env_vars": thread_env(self.spec.cpus_per_task)}
        if not self.spec.local:
            import lcv_replay
            import recorders

            env["py_modules"] = [str(Path(package.__file__).parent) for package in (lcv_replay, recorders)]
        return env

    def remote(self, fn: Callable[..., Any]):
        """``fn`` as a Ray task with this cluster's CPU and retry settings."""
        import ray

        return ray.remote(fn).options(num_cpus=self.spec.cpus_per_task, max_retries=self.spec.max_retries, retry_exceptions=False)

    def run(
        self,
        fn: Callable[..., Any],
        jobs: Iterable[J],
        *,
        args: Callable[[J], Sequence[Any]] = lambda job: (job,),
        stop: Any | None = None,  # anything with ``.requested`` (lcv_replay.replay.StopToken)
        on_submit: Callable[[J], None] | None = None,
        on_result: Callable[[TaskResult[J]], None],
    ) -> RunReport[J]:
        """Run ``fn(*args(job))`` as one task per job; call ``on_result`` as each one ends.

        At most :attr:`capacity` tasks are in flight. When ``stop.requested`` turns true, nothing
        more is submitted and the running tasks finish. ``KeyboardInterrupt`` (a second Ctrl-C)
        cancels the running tasks (reported in ``cancelled``).
        """
        import ray

        task = self.remote(fn)
        queue = collections.deque(jobs)
        inflight: dict[Any, tuple[J, float]] = {}
        try:
            while queue or inflight:
                while queue and not (stop is not None and stop.requested) and len(inflight) < self.capacity:
                    job = queue.popleft()
                    inflight[self._submit(task, args(job))] = (job, time.perf_counter())
                    if on_submit is not None:
                        on_submit(job)
                if not inflight:
                    break
                ready, _ = ray.wait(list(inflight), num_returns=1, timeout=0.5)
                if ready:
                    rest = [ref for ref in inflight if ref not in ready]
                    more, _ = ray.wait(rest, num_returns=len(rest), timeout=0) if rest else ([], [])
                    for ref in [*ready, *more]:
                        on_result(self._collect(ref, inflight.pop(ref)))
        except KeyboardInterrupt:
            cancelled = self._cancel(inflight, on_result)
            return RunReport(tuple(cancelled), tuple(queue), aborted=True)
        return RunReport((), tuple(queue), aborted=False)

    def _submit(self, task: Any, args: Sequence[Any]) -> Any:
        try:
            return task.remote(*args)
        except Exception as exc:  # a refused runtime environment, a lost connection, ...
            raise FleetError(f"Ray refused the task: {type(exc).__name__}: {first_line(str(exc))}",
                             fix="see 'ray status' and the Ray logs under /tmp/ray/session_latest/logs") from None

    def _collect(self, ref: Any, entry: tuple[J, float]) -> TaskResult[J]:
        import ray
        import ray.exceptions as rex

        job, submitted = entry
        seconds = time.perf_counter() - submitted
        try:
            return TaskResult(job, value=ray.get(ref), seconds=seconds)
        except rex.TaskCancelledError:
            return TaskResult(job, cancelled=True, seconds=seconds)
        except rex.RayError as exc:
            return TaskResult(job, failure=describe_failure(exc, max_retries=self.spec.max_retries), seconds=seconds)

    def _cancel(self, inflight: dict[Any, tuple[J, float]], on_result: Callable[[TaskResult[J]], None]) -> list[J]:
        """Cancel the running tasks (gracefully, then by force); results that still arrive are
        reported; returns the jobs that did not finish."""
        import ray

        for ref in inflight:
            ray.cancel(ref, force=False)
        deadline = time.monotonic() + CANCEL_GRACE_S
        not_run: list[J] = []
        while inflight and time.monotonic() < deadline:
            ready, _ = ray.wait(list(inflight), num_returns=len(inflight), timeout=0.2)
            for ref in ready:
                result = self._collect(ref, inflight.pop(ref))
                if result.cancelled:
                    not_run.append(result.job)
                else:
                    on_result(result)
        for ref, (job, _) in list(inflight.items()):
            ray.cancel(ref, force=True)
            not_run.append(job)
        inflight.clear()
        return not_run


def _bind_local_ray_to_loopback() -> None:
    """Make the local cluster's processes listen on 127.0.0.1 only (Ray's token authentication stays on).

    Ray reads the switch when ``ray._private.ray_constants`` is imported and passes the environment
    to the processes it starts; if that module is already loaded, its constant is set as well.
    """
    os.environ[_LOOPBACK_ENV] = "0"
    # Ray enables token authentication on a new local cluster by default and says so on stderr at
    # every start; the notice is for clusters that listen on the network, which this one does not.
    logging.getLogger("ray._private.authentication.authentication_token_setup").setLevel(logging.ERROR)
    constants = sys.modules.get("ray._private.ray_constants")
    if constants is not None:
        constants.ENABLE_RAY_CLUSTER = False
