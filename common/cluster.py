"""Connecting to Ray (the ``ray`` extra), for ``racecav eval --ray`` and ``racecav train sweep``."""

from __future__ import annotations

import os


def init(address: str):
    """The ``ray`` module, connected to the cluster at ``address`` (host:port of ``ray start
    --head``, ``auto``, ``ray://...``); "" starts a new local Ray on this machine's cores, never
    joining a cluster that another user started here.

    :raises ImportError: when ray is not installed (pip install 'racecav[ray]').
    :raises ConnectionError: when the address cannot be reached (Ray's own errors vary).
    """
    import ray

    if ray.is_initialized():
        return ray
    kw = dict(include_dashboard=False, log_to_driver=False, configure_logging=False)
    try:
        if address:
            ray.init(address=address, **kw)
        else:
            # on loopback: a local Ray talks to no other machine
            ray.init(address="local", num_cpus=os.cpu_count(), object_store_memory=100 * 2**20,
                     _node_ip_address="127.0.0.1", **kw)
    except (ConnectionError, RuntimeError, ValueError, TimeoutError) as e:
        raise ConnectionError(f"cannot connect to Ray at {address or 'a new local instance'}: "
                              f"{str(e).splitlines()[0] if str(e) else type(e).__name__}") from None
    return ray
