"""Independent jobs (one suite scene each) as Ray tasks, for suites larger than one machine.

Ray is optional (``pip install "vid2sim[ray]"``) and imported only here, only when asked for. The jobs are
plain module-level functions of this package (pickled by reference: every Ray worker needs the same vid2sim
installed) whose arguments and results are small picklable values; they read and write files through the
paths they are given, so on a cluster of several machines those paths must be on a file system every node
sees at the same place (NFS, a cluster file system). On a single machine any path works.

``address`` is ``"local"`` (start a private Ray instance on this machine for the run and stop it afterwards),
or anything :func:`ray.init` takes as ``address``: ``"auto"`` or ``"HOST:6379"`` (a running cluster, e.g.
started with ``ray start --head``), ``"ray://HOST:10001"`` (Ray Client, needs ``ray[client]``). When the
calling process is already connected to Ray (``ray.init`` was called), that connection is used as it is.
"""

from __future__ import annotations

import contextlib
from typing import Any, Callable, Iterator, Sequence

RAY_INSTALL_HINT = 'pip install "vid2sim[ray]"'


class RayUnavailable(RuntimeError):
    """Ray was asked for but is not installed, or the cluster at the given address cannot be reached."""


def import_ray():
    """The ``ray`` module, or :class:`RayUnavailable` with the install command when it is not installed."""
    try:
        import ray
    except ImportError as exc:
        raise RayUnavailable(f"--ray-address needs Ray, which is not installed: {RAY_INSTALL_HINT}") from exc
    return ray


def check_ray(address: str) -> None:
    """Fail early, before any work: Ray must be installed and a ``HOST:PORT`` address must answer.

    Raises:
        RayUnavailable: with the install command, or naming the address that does not answer.
    """
    import_ray()
    if not isinstance(address, str) or not address.strip():
        raise RayUnavailable(f"--ray-address must be 'local' or a Ray cluster address, got {address!r}")
    if address != "local":
        _check_reachable(address)


@contextlib.contextmanager
def ray_session(address: str, num_cpus: int | None = None) -> Iterator[Any]:
    """Connect to Ray at ``address`` for the duration of the ``with`` block; yields the ``ray`` module.

    Args:
        address: ``"local"`` for a private instance on this machine, else a :func:`ray.init` address.
        num_cpus: CPUs a ``"local"`` instance may use (default: Ray's count of this machine's CPUs);
            ignored when connecting to a running cluster.
    Raises:
        RayUnavailable: Ray is not installed, or it cannot connect to ``address``.
    """
    ray = import_ray()
    if not isinstance(address, str) or not address.strip():
        raise RayUnavailable(f"--ray-address must be 'local' or a Ray cluster address, got {address!r}")
    if ray.is_initialized():  # the caller's own connection (e.g. a test's ray.init): use it, leave it open
        yield ray
        return
    if address != "local":
        _check_reachable(address)
    try:
        if address == "local":
            # address="local" always starts a new instance (a bare ray.init() would join a cluster that
            # RAY_ADDRESS or a running `ray start` on this machine points to)
            ray.init(address="local", num_cpus=num_cpus, include_dashboard=False)
        else:
            ray.init(address=address)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise RayUnavailable(f"--ray-address {address}: cannot start or reach a Ray cluster there: {exc}") from exc
    try:
        yield ray
    finally:
        ray.shutdown()


def _check_reachable(address: str, timeout: float = 10.0) -> None:
    """For a ``HOST:PORT`` (or ``ray://HOST:PORT``) address, check that something accepts connections there:
    :func:`ray.init` waits for an unreachable cluster without end. Other addresses ("auto") are left to Ray."""
    import re
    import socket

    match = re.fullmatch(r"(?:ray://)?\[?([^\[\]/]+?)\]?:(\d+)", address.strip())
    if match is None:
        return
    host, port = match.group(1), int(match.group(2))
    try:
        socket.create_connection((host, port), timeout=timeout).close()
    except OSError as exc:
        raise RayUnavailable(f"--ray-address {address}: nothing accepts connections at {host}:{port} ({exc}); "
                             "start the cluster's head there (ray start --head) or pass 'local'") from None


def ray_map(fn: Callable[..., Any], calls: Sequence[tuple[tuple, dict]], address: str, num_cpus: float = 1,
            local_cpus: int | None = None, on_done: Callable[[int, Any], None] | None = None
            ) -> list[Any]:
    """Run ``fn(*args, **kwargs)`` for every ``(args, kwargs)`` of ``calls`` as one Ray task each.

    All tasks are submitted at once; Ray runs as many side by side as the cluster has room for (each task
    reserves ``num_cpus`` CPUs). Results are collected as tasks finish, in whatever order that is.

    Args:
        fn: a module-level function (pickled by reference).
        calls: the arguments of each task.
        address, local_cpus: see :func:`ray_session`.
        num_cpus: CPUs each task reserves.
        on_done: called as ``on_done(i, result)`` in the driver as soon as task i finishes (progress bars,
            incremental index files); ``result`` is the task's return value or the exception it raised.
    Returns:
        the results in the order of ``calls``; a task that raised (or whose worker died) gives its
        exception object (the task's own exception when Ray can recover it) instead of a result.
    Raises:
        RayUnavailable: see :func:`ray_session`. KeyboardInterrupt: unfinished tasks are cancelled first.
    """
    results: list[Any] = [None] * len(calls)
    if not calls:
        return results
    with ray_session(address, local_cpus) as ray:
        remote = ray.remote(num_cpus=num_cpus)(fn)
        refs = {remote.remote(*args, **kwargs): i for i, (args, kwargs) in enumerate(calls)}
        pending = list(refs)
        try:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                for ref in done:
                    i = refs[ref]
                    try:
                        results[i] = ray.get(ref)
                    except Exception as exc:  # the task raised, or its worker or node was lost
                        cause = getattr(exc, "cause", None)
                        results[i] = cause if isinstance(cause, Exception) else exc
                    if on_done is not None:
                        on_done(i, results[i])
        except KeyboardInterrupt:
            for ref in pending:
                with contextlib.suppress(Exception):
                    ray.cancel(ref, force=True)
            raise
    return results
