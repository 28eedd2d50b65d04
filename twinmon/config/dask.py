"""The ``dask`` section: the Dask cluster that runs the stages whose ``executor`` is
``dask`` (never changes a result)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional


@dataclass(frozen=True)
class DaskConfig:
    """Where the stages whose ``executor`` is ``dask`` run (docs/cluster.md).

    ``address`` null: a ``LocalCluster`` on this machine, as many worker processes as the
    stage's ``workers`` (0: one per core), one thread each; ``tcp://host:8786``: the running
    scheduler there (its workers must run one thread each). ``timeout``: seconds allowed to
    reach the scheduler or start the local workers before the command fails."""

    address: Optional[str] = None
    timeout: float = 10.0

    def _check(self):
        if self.address is not None and scheduler_host_port(self.address) is None:
            # Dask's other transports need what a config cannot give here (tls: a security
            # context; ucx, inproc: a scheduler in this process's reach): refused up front,
            # not by a traceback or a wait for the timeout.
            yield "address", "expected a TCP scheduler address such as tcp://host:8786 " \
                "(host and port; tls://, ucx:// and inproc:// are not supported), or null " \
                "for a local cluster", self.address
        if self.timeout <= 0:
            yield "timeout", "must be > 0 (seconds)", self.timeout


def scheduler_host_port(address: str) -> Optional[tuple[str, int]]:
    """``(host, port)`` of a TCP scheduler address (``tcp://host:port`` or ``host:port``,
    an IPv6 host in brackets), None for anything else (another transport, no port)."""
    if not isinstance(address, str) or not address.strip() or \
            any(c.isspace() for c in address):
        return None
    rest = address[len("tcp://"):] if address.startswith("tcp://") else address
    if "://" in rest or "/" in rest:
        return None
    host, sep, port = rest.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        return None
    return host, int(port)
