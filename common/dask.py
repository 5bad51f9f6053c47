"""Where Dask work runs: an existing cluster at an address, or a local in-process one.

Every scaled-out entry point (tiled build, tiled learning pass, experiment sweep) takes a
``dask.distributed.Client``; :func:`get_client` makes one from a ``--scheduler ADDRESS`` flag.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

from distributed import Client

CONNECT_TIMEOUT = "10s"
"""How long :func:`get_client` keeps retrying a scheduler address before it gives up (Dask's
duration string): a refused connection is retried until then."""


def get_client(address: str | None = None, threads: int | None = None) -> Client:
    """A Dask client: ``Client(address)`` for a running scheduler (e.g. ``"tcp://10.0.0.5:8786"``),
    or, with no address, an in-process cluster with ``threads`` worker threads (default: CPU count).

    The in-process default needs no serialisation or extra processes, so it is the cheap choice on one
    machine; closing the returned client also stops a cluster it started. Raises ValueError when the
    scheduler at ``address`` cannot be reached.
    """
    if address is None:
        return Client(processes=False, n_workers=1, threads_per_worker=threads or os.cpu_count() or 1,
                      dashboard_address=None)
    try:
        return Client(address, timeout=CONNECT_TIMEOUT)
    except OSError as exc:  # distributed raises OSError (TimeoutError) for an unreachable scheduler
        raise ValueError(f"--scheduler {address}: cannot connect to a Dask scheduler there ({exc})") from exc


@contextmanager
def using_client(client: Client | None = None) -> Iterator[Client]:
    """``client`` as it is, or a local :func:`get_client` for the block that is closed when the block
    ends; the caller's client is never closed."""
    if client is not None:
        yield client
        return
    own = get_client(None)
    try:
        yield own
    finally:
        own.close()
