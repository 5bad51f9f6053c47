"""One real multi-process Dask cluster shared by every test module that needs it (2 workers, 1 thread each)."""

from __future__ import annotations

import atexit
import logging

from distributed import Client, LocalCluster

_CLIENT: list[Client] = []


def shared_client() -> Client:
    """The session's client on a ``LocalCluster(n_workers=2, threads_per_worker=1, processes=True)``,
    started on first use and closed at interpreter exit (so every test module shares it)."""
    if not _CLIENT:
        cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0")
        client = Client(cluster)
        _CLIENT.append(client)

        def close() -> None:
            # At exit pytest has closed the streams its log capture wrote to: keep shutdown quiet.
            logging.getLogger("distributed").setLevel(logging.CRITICAL + 1)
            client.close()
            cluster.close()

        atexit.register(close)
    return _CLIENT[0]
