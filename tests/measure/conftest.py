"""Fixtures shared by the measurement tests."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def client():
    """A local Dask cluster of two single-threaded worker processes, one per test module."""
    from distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)
    c = Client(cluster)
    yield c
    c.close()
    cluster.close()
