"""A dask.distributed client for ``palette-decompose --workers / --scheduler``, with the
address checked before dask reads anything from it.

dask's client connects, sends its handshake and reads the scheduler's, whose first 8
bytes give the length of what follows: a port that accepts and never answers keeps it
waiting, and one that answers like a web server makes it allocate the exabytes that
``HTTP/1.1`` reads as. So a ``tcp://`` address is first probed here: a dask scheduler
sends a short handshake as soon as a connection opens (about 60 bytes), and anything
else within ``CONNECT_TIMEOUT_S`` is refused with one line. ``tls://`` needs dask's TLS
settings (``distributed.comm.tls.*``) and is probed for a connection only.
"""

from __future__ import annotations

import contextlib
import os
import socket
import struct
from urllib.parse import urlsplit

from .errors import InputError

CONNECT_TIMEOUT_S = 10.0
MAX_HANDSHAKE = 1 << 16  # bytes a scheduler's handshake may announce
SCHEMES = ("tcp", "tls")


def check_workers(workers: int | None, scheduler: str | None) -> None:
    """InputError unless ``workers`` is None or 1..the machine's cores (a local cluster),
    and not given together with ``scheduler``."""
    if workers is None:
        return
    cores = os.cpu_count() or 1
    if scheduler is not None:
        raise InputError("starts a local cluster: give it or a scheduler, not both", "workers")
    if not 1 <= workers <= cores:
        raise InputError(f"must be 1 to {cores} (this machine's cores), got {workers}", "workers")


def scheduler_address(address: str) -> tuple[str, str, int]:
    """(scheme, host, port) of ``tcp://HOST:PORT``, ``tls://HOST:PORT`` or ``HOST:PORT``.

    Raises
    ------
    InputError
        For another scheme or a malformed address.
    """
    parts = urlsplit(address if "://" in address else f"tcp://{address}")
    try:
        port = parts.port
    except ValueError:
        port = None
    if parts.scheme not in SCHEMES or not parts.hostname or port is None or parts.path:
        raise InputError(f"must be tcp://HOST:PORT or tls://HOST:PORT, got {address!r}",
                         "scheduler")
    return parts.scheme, parts.hostname, port


def probe_scheduler(address: str) -> None:
    """Fail with one line unless a dask scheduler answers at ``address`` within
    ``CONNECT_TIMEOUT_S``.

    Raises
    ------
    InputError
        If nothing listens there, it does not answer, or it answers unlike a scheduler.
    """
    scheme, host, port = scheduler_address(address)
    timeout = CONNECT_TIMEOUT_S
    if scheme == "tls":
        import dask

        if not dask.config.get("distributed.comm.tls.client.cert", None):
            raise InputError(f"{address}: tls:// needs dask's TLS settings "
                             "(distributed.comm.tls.ca-file, .client.cert, .client.key)")
    try:
        with socket.create_connection((host, port), timeout=timeout) as connection:
            if scheme == "tls":
                return
            connection.settimeout(timeout)
            header = _read(connection, 8)
    except TimeoutError:
        raise InputError(f"the dask scheduler at {address} did not answer within "
                         f"{timeout:g} s") from None
    except OSError as exc:
        raise InputError(f"cannot reach the dask scheduler at {address}: "
                         f"{exc.strerror or exc}") from None
    announced = struct.unpack("<Q", header)[0] if len(header) == 8 else 0
    if not 0 < announced <= MAX_HANDSHAKE:
        raise InputError(f"{address} does not answer like a dask scheduler")


def _read(connection: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = connection.recv(n - len(data))
        if not chunk:
            break
        data += chunk
    return data


@contextlib.contextmanager
def dask_client(workers: int | None, scheduler: str | None):
    """A dask.distributed client: of a local cluster of ``workers`` processes, or of the
    cluster at ``scheduler`` (probed first); None when neither is given.

    Raises
    ------
    InputError
        For a bad ``workers`` count or a scheduler that cannot be used.
    """
    check_workers(workers, scheduler)
    if workers is None and scheduler is None:
        yield None
        return
    from dask.distributed import Client, LocalCluster

    if scheduler is not None:
        probe_scheduler(scheduler)
        try:
            client = Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s")
        except (OSError, TimeoutError, ValueError, TypeError) as exc:
            raise InputError(f"cannot reach the dask scheduler at {scheduler}: {exc}") from None
        with client:
            yield client
        return
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster, Client(cluster) as client:
        yield client
