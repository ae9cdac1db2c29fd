"""`simgen make --ray`: the scenes as Ray tasks, on a local Ray instance or an existing cluster.

A task (:func:`scene_task`) makes its scene in memory with the same
:func:`simgen.pipeline.scene_records` as a local worker process does and returns its
:class:`~simgen.writer.SceneRecords`: the tables' rows and the bytes of every file. The records
travel through Ray's object store, and the driver writes each file once, into the dataroot,
atomically and the table part last, as for the local pool. So the workers need no filesystem
shared with the driver, and the bytes are those of the local pool, file for file.

Ray is an optional dependency (``pip install -e .[ray]``): it is imported only here, and only when
``--ray`` is given.
"""
from __future__ import annotations

import logging
import os
import re
import socket
from typing import Iterator

from .errors import ClusterError, ConfigError
from .settings import MakeSettings
from .writer import SceneRecords

LOCAL = "local"              # --ray without an ADDRESS: start a private Ray instance
CONNECT_TIMEOUT_S = 5.0      # a cluster address that does not accept a connection within this is unreachable
HANDSHAKE_TIMEOUT_S = 10.0   # a Ray head answers the gRPC handshake within this
MAX_RETRIES = 3              # Ray reruns a scene whose worker process or node was lost


def parse_address(text: str) -> str:
    """``--ray`` ADDRESS: ``auto`` or ``HOST:PORT`` (or :data:`LOCAL`). Raises ConfigError."""
    if text in (LOCAL, "auto"):
        return text
    m = re.fullmatch(r"([A-Za-z0-9.\-]+|\[[0-9A-Fa-f:]+\]):(\d{1,5})", text)
    if not m or not 1 <= int(m.group(2)) <= 65535:
        raise ConfigError(f"--ray {text!r}: give auto or HOST:PORT (e.g. 10.0.0.5:6379), or nothing "
                          f"for a local Ray instance")
    return text


def scene_task(s: MakeSettings, idx: int, threads: int) -> SceneRecords:
    """Runs on a Ray worker: scene ``idx``, made in memory."""
    if s.gl:
        os.environ["PYOPENGL_PLATFORM"] = s.gl     # as the local pool's _worker_init does
    from .pipeline import scene_records
    return scene_records(s, idx, threads)


class RayRun:
    """A connection to Ray for one `make` run: :meth:`connect`, :meth:`scenes`, :meth:`close`."""

    def __init__(self, ray, cpus: int | None):
        self.ray = ray
        self.cpus = cpus     # of a local instance; None on a cluster
        self._task = ray.remote(num_cpus=1, max_retries=MAX_RETRIES, retry_exceptions=False)(scene_task)

    @classmethod
    def connect(cls, address: str, workers: int) -> "RayRun":
        """Start a local Ray instance with ``workers`` CPUs (``address == LOCAL``), or join the
        cluster at ``auto`` or ``HOST:PORT``. No Ray installed, or a cluster that cannot be
        reached or joined, raises ClusterError before anything is written."""
        local = address == LOCAL
        if local:
            # A private instance serves only this process: it listens on the loopback interface
            # (Ray's default is every interface). Ray reads this switch when it is imported.
            os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
        try:
            import ray
        except ImportError:
            raise ClusterError("--ray needs the optional extra 'ray': pip install -e .[ray]") from None
        common = dict(log_to_driver=False, logging_level=logging.WARNING)
        if local:
            ray.init(num_cpus=workers, include_dashboard=False, **common)
            return cls(ray, cpus=workers)
        if address != "auto":
            # ray.init has no timeout of its own: at an address where no Ray cluster answers it
            # retries for many minutes. `auto` is found by ray.init, which fails at once where
            # this node runs no cluster.
            _probe(address)
        try:
            ray.init(address=address, **common)
        except (ConnectionError, RuntimeError, ValueError) as e:
            where = "a Ray cluster on this node" if address == "auto" else f"the Ray cluster at {address}"
            raise ClusterError(f"--ray {address}: cannot join {where} ({_join_failure(e)})") from None
        return cls(ray, cpus=None)

    def threads_per_task(self, todo: int) -> int:
        """Lidar threads per scene: on a local instance the cores left to each of the tasks
        running at once, as for the local pool; on a cluster a task holds one CPU."""
        if self.cpus is None:
            return 1
        return max(1, len(os.sched_getaffinity(0)) // max(1, min(self.cpus, todo)))

    def scenes(self, s: MakeSettings, todo: list[int]) -> Iterator[SceneRecords]:
        """Run the scenes ``todo`` as tasks; yield each one's records as it completes (in
        completion order). Closing the iterator early cancels the rest."""
        ray = self.ray
        settings = ray.put(s)        # one copy in the object store, not one per task
        threads = self.threads_per_task(len(todo))
        pending = {self._task.remote(settings, i, threads) for i in todo}
        try:
            while pending:
                [ref], _ = ray.wait(list(pending), num_returns=1)
                pending.remove(ref)
                records = ray.get(ref)
                del ref              # the driver's reference is the last: Ray frees the object
                yield records
        finally:
            for ref in pending:
                ray.cancel(ref, force=True)

    def close(self) -> None:
        """Disconnect; a local instance stops with its workers."""
        self.ray.shutdown()


def _probe(address: str) -> None:
    """Refuse ``HOST:PORT`` unless it accepts a connection within CONNECT_TIMEOUT_S and
    completes a gRPC handshake (a Ray head's GCS is a gRPC server) within HANDSHAKE_TIMEOUT_S."""
    host, _, port = address.rpartition(":")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=CONNECT_TIMEOUT_S).close()
    except socket.timeout:
        raise ClusterError(f"--ray {address}: cannot reach the Ray cluster at {address} "
                           f"(no answer within {CONNECT_TIMEOUT_S:g} s)") from None
    except OSError as e:
        raise ClusterError(f"--ray {address}: cannot reach the Ray cluster at {address} "
                           f"({e.strerror or e})") from None
    import grpc
    channel = grpc.insecure_channel(address)
    try:
        grpc.channel_ready_future(channel).result(timeout=HANDSHAKE_TIMEOUT_S)
    except grpc.FutureTimeoutError:
        raise ClusterError(f"--ray {address}: no Ray cluster answers at {address} (it accepts connections "
                           f"but completes no gRPC handshake within {HANDSHAKE_TIMEOUT_S:g} s)") from None
    finally:
        channel.close()


def _join_failure(e: Exception) -> str:
    """Why ``ray.init`` could not join, in a few words."""
    detail = f"{e} {e.__cause__ or ''}"
    if "InvalidAuthToken" in detail:
        # Ray sends its token unasked only to a cluster it finds itself (`auto`).
        return ("it uses Ray's token authentication: set RAY_AUTH_MODE=token, with the cluster's "
                "token in ~/.ray/auth_token")
    return str(e).splitlines()[0] if str(e) else type(e).__name__
