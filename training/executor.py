"""Where independent runs execute: in this process, a local process pool, or a Ray cluster (`--executor`).

Every command that runs many independent jobs (`bruce-eval transfer`, `walking` and `policies`, `bruce-collect
--seeds`) hands them to an `Executor` as (function, arguments) calls and gets each result back as it finishes, in any
order (PPO's environment shards, which live as long as the training, are Ray actors of the same job:
training/rl/ray_shards.py):

- `local` (default): `jobs` worker processes of this machine (`concurrent.futures.ProcessPoolExecutor`), or this
  process when `jobs` is 1.
- `ray`: Ray tasks (docs/cluster.md). `address` None starts a Ray instance on this machine; `auto` or HOST:PORT joins
  a running cluster. Every file a call needs (the robot config's folder, a policy named by `--set`) is shipped with
  the job through Ray's `runtime_env` `working_dir` (nothing is assumed on a shared disk): `where(path)` is the
  path a worker reads. A task whose worker process dies or whose node leaves is run again elsewhere by Ray
  (`max_retries`); a result reaches the caller once, when the task has finished.

A call's function must be importable by name on the workers (a module-level function of this package), and its
result must not depend on where it ran: the executors give the same results run for run.
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import tempfile
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Any

EXECUTORS = ("local", "ray")
TASK_RETRIES = 3  # Ray reruns a task whose worker died this many times before the sweep fails


class ExecutorError(RuntimeError):
    """An executor that cannot start (Ray not installed, no cluster at the address); the message says which."""


class Executor(ABC):
    """Runs independent calls; `map` yields (index in `calls`, result) as each finishes."""

    name: str

    def where(self, path: str | Path) -> str:
        """The path under which a worker reads `path` (shipped with the job where workers do not share its disk)."""
        return str(path)

    def share(self, value: Any) -> Any:
        """A handle to `value` that every call given it receives as `value` (sent to the workers once)."""
        return value

    def override(self, item: str, config: str) -> str:
        """A robot config override KEY=VALUE as a worker loading the config at `config` (as `where` names it) reads
        it: a VALUE that names a file, named as shipped. The config reader resolves a relative file beside the
        config, so a shipped file is named relative to the shipped config's folder."""
        key, _, value = item.partition("=")
        if not value or not Path(value).is_file():
            return item
        shipped = self.where(value)
        if not Path(shipped).is_absolute():
            shipped = os.path.relpath(shipped, os.path.dirname(config))
        return f"{key}={shipped}"

    def shipped_config(self, config: str | Path, overrides: Iterable[str] = ()) -> tuple[str, list[str]]:
        """A robot config and its overrides as a worker reads them (`where`, `override`)."""
        where = self.where(config)
        return where, [self.override(item, where) for item in overrides]

    @abstractmethod
    def map(self, fn: Callable, calls: Iterable[tuple]) -> Iterator[tuple[int, Any]]:
        ...

    def close(self) -> None:
        pass

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class LocalExecutor(Executor):
    """This process (`jobs` 1), or `jobs` processes of this machine."""

    name = "local"

    def __init__(self, jobs: int = 1):
        self.jobs = max(1, int(jobs))

    def map(self, fn: Callable, calls: Iterable[tuple]) -> Iterator[tuple[int, Any]]:
        calls = list(calls)
        if self.jobs == 1 or len(calls) <= 1:
            for index, args in enumerate(calls):
                yield index, fn(*args)
            return
        with ProcessPoolExecutor(max_workers=min(self.jobs, len(calls))) as pool:
            pending = {pool.submit(fn, *args): index for index, args in enumerate(calls)}
            while pending:
                done, _ = wait(pending, return_when=FIRST_COMPLETED)
                for future in done:
                    yield pending.pop(future), future.result()


class RayExecutor(Executor):
    """Ray tasks on a cluster (or a Ray instance started here), with `ship`'s files in the job's working dir."""

    name = "ray"

    def __init__(self, address: str | None = None, ship: Iterable[str | Path] = (), num_cpus: int | None = None):
        try:
            import ray
        except ImportError:
            raise ExecutorError("--executor ray: Ray is not installed (pip install -e '.[cluster]')") from None
        self._ray = ray
        self._staging = Path(tempfile.mkdtemp(prefix="bruce-job-"))
        self._shipped: dict[Path, str] = {}
        for path in sorted(Path(p).resolve() for p in ship):  # the same job, whatever order they were named in
            self._ship(path)
        # The files go with the job (Ray ships a local directory only in `ray.init`'s runtime_env), so this executor
        # connects the process itself.
        if ray.is_initialized():
            shutil.rmtree(self._staging, ignore_errors=True)
            raise ExecutorError("--executor ray: this process is connected to Ray already; the executor connects "
                                "it itself, to ship the job's files (call ray.shutdown() first)")
        try:
            _reachable(address)
            ray.init(address=address, runtime_env={"working_dir": str(self._staging)}, num_cpus=num_cpus,
                     log_to_driver=False, include_dashboard=False, logging_level="ERROR")
        except (ConnectionError, RuntimeError, ValueError) as exc:
            shutil.rmtree(self._staging, ignore_errors=True)
            raise ExecutorError(f"--ray-address {address}: cannot join a Ray cluster there ({exc})") from None

    def _ship(self, path: Path) -> str:
        """Copy a file, or a folder whole, into the job's working dir; its path there, relative to a worker's cwd."""
        path = path.resolve()
        if path not in self._shipped:
            target = Path(f"f{len(self._shipped)}") / path.name
            destination = self._staging / target
            destination.parent.mkdir(parents=True)
            if path.is_dir():
                shutil.copytree(path, destination, ignore=shutil.ignore_patterns("__pycache__"))
            else:
                shutil.copy2(path, destination)
            self._shipped[path] = target.as_posix()
        return self._shipped[path]

    def where(self, path: str | Path) -> str:
        path = Path(path).resolve()
        for shipped, target in self._shipped.items():
            if path == shipped:
                return target
            if path.is_relative_to(shipped) and shipped.is_dir():
                return f"{target}/{path.relative_to(shipped).as_posix()}"
        raise ExecutorError(f"{path}: not shipped with the Ray job (the executor was given "
                            f"{', '.join(map(str, self._shipped)) or 'no files'})")

    def share(self, value: Any) -> Any:
        return self._ray.put(value)

    def map(self, fn: Callable, calls: Iterable[tuple]) -> Iterator[tuple[int, Any]]:
        ray = self._ray
        task = ray.remote(max_retries=TASK_RETRIES)(fn)
        pending = {task.remote(*args): index for index, args in enumerate(calls)}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                yield pending.pop(ref), ray.get(ref)

    def resources(self) -> dict:
        return self._ray.cluster_resources()

    def close(self) -> None:
        if self._ray.is_initialized():
            self._ray.shutdown()
        shutil.rmtree(self._staging, ignore_errors=True)


def _reachable(address: str | None, timeout_s: float = 5.0) -> None:
    """A HOST:PORT that nothing answers at fails here, in seconds (Ray's own connect retries for minutes)."""
    if not address or address == "auto" or "://" in address:
        return
    host, _, port = address.rpartition(":")
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except (OSError, ValueError) as exc:
        raise ConnectionError(f"no Ray head answers there: {exc}") from None


def job_files(config: str | Path, overrides: Iterable[str] = (), files: Iterable[str | Path] = ()) -> set[Path]:
    """What a run reads from disk, to ship with the job: the robot config's folder, every file an override
    KEY=VALUE names, and `files`."""
    named = (item.partition("=")[2] for item in overrides)
    return {Path(config).resolve().parent, *(Path(v).resolve() for v in named if v and Path(v).is_file()),
            *(Path(f).resolve() for f in files)}


def add_executor_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--executor", choices=EXECUTORS, default="local",
                   help="where the runs execute: local (this machine, --jobs processes) or ray (a Ray cluster: "
                        "docs/cluster.md) (default: %(default)s)")
    p.add_argument("--ray-address", default=None, metavar="ADDRESS",
                   help="with --executor ray: a running cluster's HOST:PORT, or auto (RAY_ADDRESS, or the cluster "
                        "`ray start` began on this machine); without it, Ray starts on this machine alone")


def make_executor(args: argparse.Namespace, jobs: int, ship: Iterable[str | Path] = ()) -> Executor:
    """The executor the command line asks for (`add_executor_arguments`)."""
    if args.executor == "ray":
        return RayExecutor(args.ray_address, ship)
    if args.ray_address is not None:
        raise ExecutorError("--ray-address: only with --executor ray")
    return LocalExecutor(jobs)
