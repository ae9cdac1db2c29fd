"""`simgen make --ray`: the scenes as Ray tasks, on a local Ray instance or an existing cluster.

A task runs the same :func:`simgen.pipeline.generate_scene` as a local worker process does, into a
scratch folder on its own node, and returns the bytes of every file the scene wrote: its *part*
(the JPEGs, ``.pcd.bin`` sweeps, lidarseg labels, the map and the table part
``.parts/scene-NNNN.json``). The results travel through Ray's object store, and the driver writes
each file into the dataroot atomically, the table part last: it is the mark that a scene is done,
as for the local pool. So the workers need no filesystem shared with the driver, and the bytes are
those of the local pool, file for file.

Ray is an optional dependency (``pip install -e .[ray]``): it is imported only here, and only when
``--ray`` is given.
"""
from __future__ import annotations

import logging
import os
import re
import shutil
import signal
import socket
import sys
import tempfile
import threading
from pathlib import Path
from typing import Iterator

from . import writer as W
from .config import ConfigError
from .settings import MakeSettings

LOCAL = "local"              # --ray without an ADDRESS: start a private Ray instance
CONNECT_TIMEOUT_S = 5.0      # a cluster address that does not answer within this is unreachable
JOIN_TIMEOUT_S = 30.0        # joining a cluster that answers takes a few seconds
MAX_RETRIES = 3              # Ray reruns a scene whose worker process or node was lost
# Test-only: "SCENE:MARKER" makes the first attempt at that scene kill its own worker process
# (SIGKILL, after rendering, before its bytes are returned) and create MARKER, so that Ray's
# retry, which finds MARKER, goes through. Used by tests/simgen/test_ray.py.
TEST_KILL_ENV = "SIMGEN_TEST_KILL_RAY_WORKER"


def parse_address(text: str) -> str:
    """``--ray`` ADDRESS: ``auto`` or ``HOST:PORT`` (or :data:`LOCAL`). Raises ConfigError."""
    if text in (LOCAL, "auto"):
        return text
    m = re.fullmatch(r"([A-Za-z0-9.\-]+|\[[0-9A-Fa-f:]+\]):(\d{1,5})", text)
    if not m or not 1 <= int(m.group(2)) <= 65535:
        raise ConfigError(f"--ray {text!r}: give auto or HOST:PORT (e.g. 10.0.0.5:6379), or nothing "
                          f"for a local Ray instance")
    return text


class RayRun:
    """A connection to Ray for one `make` run: :meth:`connect`, :meth:`scenes`, :meth:`close`."""

    def __init__(self, ray, cpus: int | None):
        self.ray = ray
        self.cpus = cpus     # of a local instance; None on a cluster
        self._task = ray.remote(num_cpus=1, max_retries=MAX_RETRIES, retry_exceptions=False)(scene_files)

    @classmethod
    def connect(cls, address: str, workers: int) -> "RayRun":
        """Start a local Ray instance with ``workers`` CPUs (``address == LOCAL``), or join the
        cluster at ``auto`` or ``HOST:PORT``. Bad input (no Ray installed, an unreachable cluster)
        raises ConfigError before anything is written."""
        local = address == LOCAL
        if local:
            # A private instance serves only this process: it listens on the loopback interface
            # (Ray's default is every interface). Ray reads this switch when it is imported.
            os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
        try:
            import ray
        except ImportError:
            raise ConfigError("--ray needs the optional extra 'ray': pip install -e .[ray]") from None
        common = dict(log_to_driver=False, logging_level=logging.WARNING)
        if local:
            ray.init(num_cpus=workers, include_dashboard=False, **common)
            return cls(ray, cpus=workers)
        host_port = _cluster_address(address)
        _probe(address, host_port)
        # ray.init has no timeout of its own: at an address that accepts connections but is no
        # Ray cluster (a dashboard port, say) it retries for many minutes.
        watchdog = threading.Timer(JOIN_TIMEOUT_S, _give_up, args=(address, host_port))
        watchdog.daemon = True
        watchdog.start()
        try:
            ray.init(address=host_port, **common)
        except (ConnectionError, RuntimeError) as e:
            raise ConfigError(f"--ray {address}: cannot join the Ray cluster at {host_port} "
                              f"({_join_failure(e)})") from None
        finally:
            watchdog.cancel()
        return cls(ray, cpus=None)

    def threads_per_task(self, todo: int) -> int:
        """Lidar threads per scene: on a local instance the cores left to each of the tasks
        running at once, as for the local pool; on a cluster a task holds one CPU."""
        if self.cpus is None:
            return 1
        return max(1, len(os.sched_getaffinity(0)) // max(1, min(self.cpus, todo)))

    def scenes(self, s: MakeSettings, dataroot: Path, todo: list[int]) -> Iterator[tuple[int, int]]:
        """Run the scenes ``todo`` as tasks; write each one's files as it completes (in completion
        order) and yield ``(scene index, samples)``. Closing the iterator early cancels the rest."""
        ray = self.ray
        settings = ray.put(s)        # one copy in the object store, not one per task
        threads = self.threads_per_task(len(todo))
        pending = {self._task.remote(settings, i, threads): i for i in todo}
        try:
            while pending:
                [ref], _ = ray.wait(list(pending), num_returns=1)
                idx = pending.pop(ref)
                n_samples, files = ray.get(ref)
                del ref              # the driver's reference is the last: Ray frees the object
                write_scene(dataroot, idx, files)
                del files
                yield idx, n_samples
        finally:
            for ref in pending:
                ray.cancel(ref, force=True)

    def close(self) -> None:
        """Disconnect; a local instance stops with its workers."""
        self.ray.shutdown()


def scene_files(s: MakeSettings, idx: int, threads: int) -> tuple[int, dict[str, bytes]]:
    """Runs on a Ray worker: scene ``idx`` made into a scratch folder on the worker's node.
    Returns its number of samples and ``{path relative to the dataroot: bytes}`` of every file
    it wrote."""
    if s.gl:
        os.environ["PYOPENGL_PLATFORM"] = s.gl     # as the local pool's _worker_init does
    from .pipeline import generate_scene
    with tempfile.TemporaryDirectory(prefix=f"simgen-scene-{idx:04d}-") as tmp:
        root = Path(tmp)
        n_samples = generate_scene(s, root, idx, threads)
        _test_kill_once(idx, root)
        files = {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}
    return n_samples, files


def write_scene(dataroot: Path, idx: int, files: dict[str, bytes]) -> None:
    """Write a scene's files into ``dataroot``, each through a temporary name and a rename, its
    table part last: until that exists, a rerun makes the scene again."""
    part = W.part_path(Path(), idx).as_posix()
    assert part in files, f"scene {idx}: no table part among its {len(files)} files"
    for rel, data in files.items():
        # The paths come from another process, maybe another machine: they stay inside dataroot.
        assert not rel.startswith("/") and ".." not in Path(rel).parts, rel
        if rel != part:
            W.write_atomic(dataroot / rel, data)
    W.write_atomic(dataroot / part, files[part])


def _cluster_address(address: str) -> str:
    """``HOST:PORT`` of the cluster to join: as given, or for ``auto`` the one that ``ray start``
    recorded on this node (or ``$RAY_ADDRESS``), found as ``ray.init`` finds it."""
    if address != "auto":
        return address
    try:
        from ray._private.services import canonicalize_bootstrap_address
        found = canonicalize_bootstrap_address("auto")
    except ConnectionError:
        found = None
    except ValueError as e:          # a malformed $RAY_ADDRESS
        raise ConfigError(f"--ray auto: {e}") from None
    if found is None:
        raise ConfigError("--ray auto: no Ray cluster is running on this node (start one with "
                          "`ray start --head`, or give HOST:PORT)")
    return found


def _probe(address: str, host_port: str) -> None:
    """Refuse an address where nothing answers, within CONNECT_TIMEOUT_S: ``ray.init`` itself
    retries an unreachable address for many minutes."""
    host, _, port = host_port.rpartition(":")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=CONNECT_TIMEOUT_S).close()
    except socket.timeout:
        reason = f"no answer within {CONNECT_TIMEOUT_S:g} s"
    except OSError as e:
        reason = e.strerror or str(e)
    else:
        return
    where = host_port if address == host_port else f"{host_port}, found by {address}"
    raise ConfigError(f"--ray {address}: cannot reach the Ray cluster at {where} ({reason})")


def _join_failure(e: Exception) -> str:
    """Why ``ray.init`` could not join, in a few words."""
    detail = f"{e} {e.__cause__ or ''}"
    if "InvalidAuthToken" in detail:
        # Ray sends its token unasked only to a cluster it finds itself (`auto`).
        return ("it uses Ray's token authentication: set RAY_AUTH_MODE=token, with the cluster's "
                "token in ~/.ray/auth_token")
    return str(e).splitlines()[0] if str(e) else type(e).__name__


def _give_up(address: str, host_port: str) -> None:
    """The end of a join that did not complete within JOIN_TIMEOUT_S. The cluster is joined before
    anything is written, so ending the process here leaves nothing half-done."""
    print(f"simgen: error: --ray {address}: no Ray cluster answers at {host_port} "
          f"(joining it took over {JOIN_TIMEOUT_S:g} s)", file=sys.stderr, flush=True)
    os._exit(2)      # simgen.cli's exit code for bad input; the main thread is stuck inside Ray


def _test_kill_once(idx: int, scratch: Path) -> None:
    """The test-only hook of :data:`TEST_KILL_ENV` (a no-op unless that variable is set). The
    scratch folder goes first, so that the test leaves nothing behind in the temporary folder."""
    hook = os.environ.get(TEST_KILL_ENV)
    if not hook:
        return
    scene, _, marker = hook.partition(":")
    if int(scene) == idx and not os.path.exists(marker):
        Path(marker).touch()
        shutil.rmtree(scratch)
        os.kill(os.getpid(), signal.SIGKILL)
