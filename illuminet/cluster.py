"""Offline jobs on Ray: shards, their store on disk, retries, progress and the end-of-job summary.

The one module that imports Ray (``pip install 'illuminet[cluster]'``), and only inside
:func:`run_shards`: ``illuminet datagen / train --objects / eval`` without ``--ray`` never import it.

A job is a list of :class:`Shard` s, each a deterministic function of its arguments (seeds included)
that returns the shard's files as ``{relative name: bytes}``. The driver (the machine that runs the
command) submits the shards that are not done yet, and writes each result as it arrives into the
job's :class:`ShardStore` (a folder keyed by shard: every file written to a temporary name and
renamed, a completion marker last). So:

* results travel back through Ray's object store and only the driver writes: the output folder
  needs to exist on the driver's machine only, not on a shared file system (docs/cluster.md);
* a restarted run skips the shards whose marker exists and redoes only the rest; a shard that was
  half written has no marker and is redone;
* a task whose worker dies (killed, out of memory, node lost) or that raises is resubmitted up to
  ``retries`` times by the driver (Ray's own ``max_retries`` is 0, so that one bound covers both and
  the summary can count them), then reported with its error in ``<store>/.errors/<key>.txt``; the
  other shards go on and what was written stays;
* the command merges the finished shards into the same output as its single-machine path.

Without an address :func:`run_shards` starts Ray on this machine (``--ray-workers`` CPUs, a small
object store) and stops it at the end; with one it joins that cluster (``ray start --head``
elsewhere). A Ray already initialised in this process (tests, notebooks) is used as it is.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import socket
import sys
import time
from collections import deque
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from illuminet.runtime.errors import EXIT_USAGE, JobError

log = logging.getLogger("illuminet.cluster")

#: ``--ray`` without an address: start Ray on this machine
LOCAL = "local"
#: object store of a local Ray: shard results are a few MB each; Ray's default (30 % of RAM) is far
#: more than a shared 2-core machine should give away
LOCAL_OBJECT_STORE_BYTES = 256 * 1024 * 1024
#: the completion marker of a shard folder (unless the job names one of its own files)
MARKER = ".shard-done"
JOB_FILE = "job.json"
ERRORS = ".errors"


class RayUnavailable(JobError):
    """``--ray`` without Ray installed (exit 2)."""

    exit_code = EXIT_USAGE


class ShardStoreError(JobError):
    """A shard folder that belongs to another job: different parameters (exit 2)."""

    exit_code = EXIT_USAGE


class JobFailed(JobError):
    """Some shards failed after their retries; the others are kept on disk (exit 1)."""


# ------------------------------------------------------------------------------------ arguments


def add_arguments(p: argparse.ArgumentParser, unit: str = "shard") -> None:
    """``--ray [ADDRESS]``, ``--ray-workers N`` and ``--ray-retries N`` on a command's parser."""
    g = p.add_argument_group("Ray (run the work as shards on a Ray cluster; docs/cluster.md)")
    g.add_argument(
        "--ray",
        nargs="?",
        const=LOCAL,
        default=None,
        metavar="ADDRESS",
        help=f"run one Ray task per {unit}: without ADDRESS Ray starts on this machine; with one "
        "(host:6379, auto, ray://host:10001) it joins that cluster. Needs: pip install 'illuminet[cluster]'",
    )
    g.add_argument(
        "--ray-workers",
        type=int,
        default=None,
        metavar="N",
        help="local Ray: CPUs (parallel tasks) it may use (default: every core of this machine); "
        "a cluster: at most N tasks in flight (default: 2 per CPU of the cluster)",
    )
    g.add_argument(
        "--ray-retries",
        type=int,
        default=2,
        metavar="N",
        help="times a failed task (exception or dead worker) is resubmitted before it is reported (default 2)",
    )


def check_arguments(args: argparse.Namespace) -> None:
    """Usage errors of the Ray flags (before any work)."""
    if args.ray_workers is not None and args.ray_workers < 1:
        raise JobError(f"--ray-workers must be >= 1, got {args.ray_workers}", exit_code=EXIT_USAGE)
    if args.ray_retries < 0:
        raise JobError(f"--ray-retries must be >= 0, got {args.ray_retries}", exit_code=EXIT_USAGE)
    if args.ray_workers is not None and args.ray is None:
        raise JobError("--ray-workers needs --ray (it sets how many Ray tasks run at once)", exit_code=EXIT_USAGE)
    if args.ray is not None:
        import importlib.util

        if importlib.util.find_spec("ray") is None:  # before any work; import_ray says the same later
            raise RayUnavailable("--ray needs Ray, which is not installed: pip install 'illuminet[cluster]'")


# ------------------------------------------------------------------------------------ the shard store


@dataclass
class Shard:
    """One deterministic piece of a job.

    key : str
        Unique in the job and usable as a folder name (letters, digits, ``-_.``).
    fn : callable
        A module-level function (workers import it by name): ``fn(*args) -> {name: bytes}``, the
        shard's files (``name`` relative, ``/`` allowed; never ``..``).
    args : tuple
        Its arguments (pickled to the workers; large arrays go once through the object store).
    items : int
        Units of work in the shard (samples, scenes, objects) for the throughput figure.
    """

    key: str
    fn: Callable[..., dict[str, bytes]]
    args: tuple = ()
    items: int = 1


def _write_atomic(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


class ShardStore:
    """The folder of a job's results: ``<root>/<key>/<files>``, done when ``<key>/<marker>`` exists.

    marker : the completion marker: :data:`MARKER` (written after the files), or the name of one of
        the shard's own files that the job writes last (``bundle.json`` for trained bundles).
    """

    def __init__(self, root: str | Path, marker: str = MARKER):
        self.root = Path(root)
        self.marker = marker

    def path(self, key: str) -> Path:
        return self.root / key

    def is_done(self, key: str) -> bool:
        return (self.root / key / self.marker).is_file()

    def read(self, key: str, name: str) -> bytes:
        return (self.root / key / name).read_bytes()

    def write(self, key: str, files: dict[str, bytes], info: dict | None = None) -> None:
        """Every file atomically, then the marker (a crash in between leaves the shard not done)."""
        folder = self.root / key
        for name, data in files.items():
            if name == self.marker:
                continue
            _write_atomic(self._inside(folder, name), data)
        if self.marker in files:
            _write_atomic(folder / self.marker, files[self.marker])
        else:
            _write_atomic(folder / self.marker, (json.dumps(info or {}, sort_keys=True) + "\n").encode())
        err = self.root / ERRORS / f"{key}.txt"
        if err.is_file():
            err.unlink()

    def write_error(self, key: str, text: str) -> Path:
        path = self.root / ERRORS / f"{key}.txt"
        _write_atomic(path, text.encode())
        return path

    def check_job(self, job: dict) -> None:
        """Record the job's parameters (``job.json``), or refuse a folder that holds another job's shards."""
        path = self.root / JOB_FILE
        want = json.loads(json.dumps(job, sort_keys=True))
        if path.is_file():
            try:
                have = json.loads(path.read_text())
            except (OSError, json.JSONDecodeError):
                have = None
            if have != want:
                diff = sorted(k for k in set(want) | set(have or {}) if (have or {}).get(k) != want.get(k))
                raise ShardStoreError(
                    f"{self.root} holds shards of another job (different {', '.join(diff) or 'parameters'}): "
                    "delete that folder or choose another --out"
                )
            return
        _write_atomic(path, (json.dumps(want, indent=1, sort_keys=True) + "\n").encode())

    def remove(self) -> None:
        shutil.rmtree(self.root, ignore_errors=True)

    @staticmethod
    def _inside(folder: Path, name: str) -> Path:
        p = Path(name)
        if p.is_absolute() or ".." in p.parts or not p.parts:
            raise ValueError(f"shard file name {name!r} must be a relative path inside the shard folder")
        return folder / p


# ------------------------------------------------------------------------------------ the summary


@dataclass
class JobSummary:
    """What :func:`run_shards` did (also the end-of-job line)."""

    name: str
    unit: str
    total: int  # shards of the job
    skipped: int = 0  # done by an earlier run (kept, not recomputed)
    done: int = 0  # finished by this run
    failed: int = 0
    retried: int = 0  # resubmissions (exceptions and dead workers)
    items: int = 0  # units of work finished by this run
    wall_s: float = 0.0
    task_s: float = 0.0  # the finished shards' own run times, summed (busy time of the workers)
    errors: dict[str, str] = field(default_factory=dict)  # key -> last error (one line)
    dashboard_url: str | None = None
    workers: str = ""

    @property
    def complete(self) -> bool:
        return self.skipped + self.done == self.total

    def line(self) -> str:
        rate = self.items / self.wall_s if self.wall_s > 0 else 0.0
        parts = [
            f"{self.name} on Ray ({self.workers}): {self.total} shards: {self.done} done"
            + (f" (+{self.skipped} from an earlier run)" if self.skipped else ""),
            f"{self.failed} failed",
            f"{self.retried} retried",
            f"wall {self.wall_s:.1f} s",
            f"{self.items} {self.unit}s at {rate:.3g} {self.unit}s/s",
        ]
        if self.task_s > 0 and self.wall_s > 0:
            parts.append(f"tasks busy {self.task_s:.1f} s ({self.task_s / self.wall_s:.2f} in parallel on average)")
        return ", ".join(parts)


# ------------------------------------------------------------------------------------ Ray


def _run_shard(fn, *args):
    """What a Ray task runs: the shard function, its wall time and where it ran (arguments at the top
    level, so that Ray resolves those passed as object references)."""
    t0 = time.perf_counter()
    files = fn(*args)
    if not isinstance(files, dict) or not all(isinstance(k, str) and isinstance(v, bytes) for k, v in files.items()):
        raise TypeError(f"shard function {fn.__module__}.{fn.__qualname__} must return {{name: bytes}}")
    return files, {"seconds": round(time.perf_counter() - t0, 3), "host": socket.gethostname(), "pid": os.getpid()}


def import_ray():
    """Ray, or :class:`RayUnavailable` with the one line that says how to install it."""
    try:
        import ray
    except ImportError as e:
        raise RayUnavailable(
            f"--ray needs Ray ({e.name or 'ray'} is not importable): pip install 'illuminet[cluster]'"
        ) from None
    return ray


def _describe(ray, exc: BaseException) -> str:
    """One line for a failed attempt: the task's own exception, or how its worker went away."""
    if isinstance(exc, ray.exceptions.RayTaskError):
        cause = getattr(exc, "cause", None)
        if cause is not None and not isinstance(cause, ray.exceptions.RayTaskError):
            return f"{type(cause).__name__}: {str(cause).strip().splitlines()[-1] if str(cause).strip() else ''}"
        return str(exc).strip().splitlines()[-1]
    first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    return f"worker lost ({type(exc).__name__}): {first}"


#: (dashboard URL, description) of the Ray session opened by :func:`ray_session`, for run_shards' lines
_SESSION: dict[str, Any] = {}


@contextmanager
def ray_session(address: str = LOCAL, workers: int | None = None, quiet: bool = False, stream=None):
    """Ray for the ``with`` block: started on this machine (``address`` :data:`LOCAL`: ``workers``
    CPUs, a small object store), joined (any other address), or the instance this process already
    runs (left running). Yields the ``ray`` module; Ray is shut down after the block if it was
    started or joined here. Several :func:`run_shards` calls in one block share the instance."""
    ray = import_ray()
    if ray.is_initialized():
        outer = bool(_SESSION)  # a session of ours around this one, or Ray started by the caller
        if not outer:
            cpus = int(ray.cluster_resources().get("CPU", 0))
            _SESSION.update(url=None, desc=f"the running Ray instance, {cpus} CPUs")
        try:
            yield ray
        finally:
            if not outer:
                _SESSION.clear()
        return
    kw: dict[str, Any] = {"logging_level": logging.WARNING, "log_to_driver": not quiet}
    if address == LOCAL:
        n = workers or os.cpu_count() or 1
        ctx = ray.init(num_cpus=n, object_store_memory=LOCAL_OBJECT_STORE_BYTES, **kw)
        desc = f"local, {n} worker{'s' if n != 1 else ''}"
    else:
        ctx = ray.init(address=address, **kw)
        desc = f"cluster {address}, {int(ray.cluster_resources().get('CPU', 0))} CPUs"
    url = getattr(ctx, "dashboard_url", None) or None
    if url and not url.startswith("http"):
        url = "http://" + url
    if url:
        print(f"Ray dashboard (progress of every task): {url}", file=stream if stream is not None else sys.stderr)
    _SESSION.update(url=url, desc=desc)
    try:
        yield ray
    finally:
        _SESSION.clear()
        ray.shutdown()


def run_shards(
    name: str,
    shards: list[Shard],
    store: ShardStore,
    *,
    address: str = LOCAL,
    workers: int | None = None,
    retries: int = 2,
    unit: str = "shard",
    show_progress: bool = True,
    stream=None,
) -> JobSummary:
    """Run the shards that ``store`` does not hold yet on Ray; write each result as it arrives.

    Returns the :class:`JobSummary` (``complete`` when every shard is in the store). Shards that failed
    ``retries + 1`` times are in ``summary.errors`` and ``<store>/.errors/<key>.txt``; the caller
    decides whether to merge (only when complete) and how to exit.
    """
    keys = [s.key for s in shards]
    if len(set(keys)) != len(keys):
        raise ValueError(f"job {name}: shard keys must be unique")
    summary = JobSummary(name=name, unit=unit, total=len(shards))
    todo = deque()
    for s in shards:
        if store.is_done(s.key):
            summary.skipped += 1
        else:
            todo.append((s, 0))
    stream = stream if stream is not None else sys.stderr
    if summary.skipped:
        print(
            f"{name}: {summary.skipped} of {len(shards)} shards are done in {store.root} (kept); {len(todo)} to run",
            file=stream,
        )
    if not todo:
        summary.workers = "nothing to run"
        return summary

    with ray_session(address, workers, quiet=not show_progress, stream=stream) as ray:
        summary.workers, summary.dashboard_url = _SESSION.get("desc", ""), _SESSION.get("url")
        _drive(ray, name, todo, store, summary, address, workers, retries, unit, show_progress, stream)
    return summary


def _drive(ray, name, todo, store, summary, address, workers, retries, unit, show_progress, stream) -> None:
    """Submit, wait, write, resubmit: the driver's loop of :func:`run_shards`."""
    from illuminet.progress import StatusLine, format_job

    status = StatusLine(stream, enabled=None if show_progress else False, formatter=format_job)
    t0 = time.perf_counter()
    last_log = t0
    inflight: dict[Any, tuple[Shard, int]] = {}
    try:
        task = ray.remote(num_cpus=1, max_retries=0)(_run_shard)
        cpus = max(int(ray.cluster_resources().get("CPU", 1)), 1)
        limit = workers if (workers and address != LOCAL) else 2 * cpus
        # the shards' large arguments (meshes, data specs, configurations) go into the object store once
        put_cache: dict[int, Any] = {}

        def put(a):
            if isinstance(a, (str, int, float, bool, type(None))):
                return a
            k = id(a)
            if k not in put_cache:
                put_cache[k] = ray.put(a)
            return put_cache[k]

        while todo or inflight:
            while todo and len(inflight) < limit:
                shard, attempt = todo.popleft()
                ref = task.remote(shard.fn, *(put(a) for a in shard.args))
                inflight[ref] = (shard, attempt)
            ready, _ = ray.wait(list(inflight), num_returns=1, timeout=0.5)
            for ref in ready:
                shard, attempt = inflight.pop(ref)
                try:
                    files, info = ray.get(ref)
                except ray.exceptions.RayError as e:
                    msg = _describe(ray, e)
                    if attempt < retries:
                        summary.retried += 1
                        status.clear()
                        log.warning("%s: shard %s failed (attempt %d): %s; retrying", name, shard.key, attempt + 1, msg)
                        todo.appendleft((shard, attempt + 1))
                    else:
                        summary.failed += 1
                        summary.errors[shard.key] = msg
                        path = store.write_error(shard.key, f"{msg}\n\n{e}\n")
                        status.clear()
                        print(
                            f"{name}: shard {shard.key} failed after {attempt + 1} attempt(s): {msg} (details: {path})",
                            file=stream,
                        )
                    continue
                info.update(key=shard.key, attempts=attempt + 1)
                store.write(shard.key, files, info)
                summary.done += 1
                summary.items += shard.items
                summary.task_s += info["seconds"]
            now = time.perf_counter()
            snap = {
                "name": name,
                "unit": unit,
                "finished": summary.skipped + summary.done,
                "total": summary.total,
                "running": len(inflight),
                "failed": summary.failed,
                "retried": summary.retried,
                "items": summary.items,
                "elapsed_s": now - t0,
            }
            status.update(snap)
            if not status.enabled and show_progress and (now - last_log > 10 or (not todo and not inflight)):
                last_log = now
                log.info("%s", format_job(snap))
    except KeyboardInterrupt:
        status.close()
        for ref in inflight:
            ray.cancel(ref, force=True)
        print(
            f"{name}: interrupted; {summary.skipped + summary.done} of {summary.total} shards are kept in "
            f"{store.root}: run the same command again to finish",
            file=stream,
        )
        raise
    finally:
        status.close()
        summary.wall_s = time.perf_counter() - t0


def finish(summary: JobSummary, store: ShardStore, stream=None) -> None:
    """Print the summary; raise :class:`JobFailed` (exit 1) when shards are missing."""
    print(summary.line(), file=stream if stream is not None else sys.stdout)
    if not summary.complete:
        worst = "; ".join(f"{k}: {v}" for k, v in list(summary.errors.items())[:3])
        raise JobFailed(
            f"{summary.name}: {summary.total - summary.skipped - summary.done} of {summary.total} shards failed "
            f"({worst}); the {summary.skipped + summary.done} finished ones are kept in {store.root}: "
            "run the same command again to redo only the failed ones"
        )
