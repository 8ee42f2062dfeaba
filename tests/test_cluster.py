"""The Dask cluster parallel work runs on: a task that asks for a cluster of its own (a
validation study that runs a design search on a validation worker) gets one it can use."""

from __future__ import annotations

import numpy as np


def _use(shared: np.ndarray, v: int) -> float:
    return float(shared.sum()) + v


def _a_task_with_a_cluster(x: int) -> float:
    from bayesrob.cluster import dask_client, share

    # a LocalCluster of processes here would fail: a worker's processes are daemons
    with dask_client(None, 2) as client:
        shared = share(client, np.ones(100))
        return sum(client.gather([client.submit(_use, shared, v, pure=False)
                                  for v in range(4)])) + x


def test_a_task_that_asks_for_a_cluster_gets_one_it_can_share_values_on():
    from bayesrob.cluster import dask_client, share

    with dask_client(None, 2) as client:
        assert client.gather(client.map(_a_task_with_a_cluster, [0, 1])) == [406.0, 407.0]
        shared = share(client, np.ones(10))  # outside a task: scattered to every worker
        assert client.gather(client.submit(_use, shared, 1)) == 11.0
