"""Dask clients for a run on workers: a local cluster, a scheduler's address, an encrypted ``tls://`` one.

``clrecon run --workers N`` (a local cluster of N single-threaded worker processes) or
``--cluster ADDRESS`` (an existing scheduler; docs/distributed.md has the SLURM recipe), and
``clrecon.run(..., client=...)`` in Python. The run itself is the same graph of stages as in
one process; :mod:`clrecon.pipeline.executors.dask` sends its units (:mod:`clrecon.pipeline.work_units`)
to the workers and writes each result, as it arrives, with the run's own writers (atomic,
checksummed, the same files as in one process), so volumes and metrics are bit-identical to a
single-process run. A worker killed mid-unit costs only that unit (Dask gives it to another
worker; nothing was written); a client killed or interrupted keeps every unit written so far,
and the rerun computes only the rest.

Needs ``dask[distributed]`` (``pip install 'clrecon[dask]'``), imported only when used. On a
cluster the projection store folder (``--cache``) and the run directory must be paths every
worker and the client see (a shared file system): the workers read the store.

A ``tls://`` scheduler (patient data) is reached with Dask's TLS security
(:func:`tls_security`: a CA file and the client's certificate and key, from ``--tls-ca-file``,
``--tls-cert``, ``--tls-key`` or Dask's config ``distributed.comm.tls.*``); every message
between client, scheduler and workers is then encrypted and both ends are authenticated by
the cluster's CA (docs/distributed.md).
"""

from __future__ import annotations

import contextlib
import logging
import os
import ssl
from collections.abc import Iterator
from typing import Any

from clrecon.core import drivers
from clrecon.core.errors import ClreconError
from clrecon.pipeline import work_units

INSTALL_HINT = "pip install 'clrecon[dask]' (dask[distributed] >= 2024.1)"


def dask_module():
    """The ``distributed`` package, or a one-line error naming what to install."""
    try:
        import distributed
    except ImportError:
        raise ClreconError(f"--workers/--cluster/client= need Dask, which is not installed: {INSTALL_HINT}") from None
    return distributed


# ----------------------------------------------------------------------------------------
# clients
def runtime_plugin(device: str | None = None):
    """A Dask worker plugin that builds each worker's OpenCL runtime once, when the worker starts.

    Registered on the scheduler, it also runs on workers that join later (a restarted one, a
    new SLURM job). ``device``: a ``CLRECON_DEVICE`` spec forced on every worker; None keeps
    each worker's own environment (the SLURM recipe sets it per job).
    """
    from distributed.diagnostics.plugin import WorkerPlugin

    class ClreconRuntime(WorkerPlugin):
        name = "clrecon-runtime"
        idempotent = True

        def setup(self, worker):
            worker.clrecon_device = work_units.prepare_worker(device)

    return ClreconRuntime()


def preference_plugin(key: str, reason: str):
    """A Dask worker plugin that makes CPU driver ``key`` each worker's preferred driver (:func:`clrecon.core.
    drivers.prefer`): the run's timed choice (:mod:`clrecon.pipeline.driver_choice`), so that the units use the
    driver the client chose and a run's outputs do not depend on where its units ran. Registered again by each
    run (same name: it replaces the last run's)."""
    from distributed.diagnostics.plugin import WorkerPlugin

    class ClreconDriverPreference(WorkerPlugin):
        name = "clrecon-driver-preference"

        def setup(self, worker):
            drivers.prefer(key, reason)

    return ClreconDriverPreference()


#: The command line's certificate options, in the order of :func:`tls_security`'s arguments.
TLS_FLAGS = ("--tls-ca-file", "--tls-cert", "--tls-key")
_TLS_CONFIG = ("distributed.comm.tls.ca-file", "distributed.comm.tls.client.cert", "distributed.comm.tls.client.key")
_TLS_HOWTO = ("give --tls-ca-file CA.pem --tls-cert CLIENT.pem --tls-key CLIENT.key, or set "
              "distributed.comm.tls.ca-file and distributed.comm.tls.client.cert/key in Dask's config "
              "(docs/distributed.md)")


def is_tls(address: str | None) -> bool:
    """Whether a scheduler address is a ``tls://`` one."""
    return address is not None and str(address).strip().lower().startswith("tls://")


def tls_security(ca_file: str | None = None, cert: str | None = None, key: str | None = None, *,
                 address: str = "") -> Any:
    """A ``distributed.Security`` for a client of the ``tls://`` scheduler at ``address``.

    ``ca_file``: PEM file of the CA that signed the cluster's certificates (the scheduler's and
    workers' certificates are checked against it); ``cert``/``key``: the client's PEM
    certificate and private key (``key`` may be omitted when it is appended to ``cert``).
    With none of the three given, they come from Dask's config (``distributed.comm.tls.ca-file``,
    ``distributed.comm.tls.client.cert`` / ``.key``). Encryption is required. Every file is
    read and the TLS context built here, so an unreadable or mismatched file is a one-line
    :class:`ClreconError` naming the option (or config key) and the file, before any
    connection is tried.
    """
    d = dask_module()
    given = (ca_file, cert, key)
    if any(v is not None for v in given):
        names = TLS_FLAGS
        if ca_file is None or cert is None:
            missing = [f for f, v in zip(TLS_FLAGS[:2], given[:2], strict=True) if v is None]
            raise ClreconError(f"--cluster {address}: {' and '.join(missing)} missing: a tls:// scheduler needs the "
                               f"cluster's CA file and the client's certificate (with --tls-key, unless the key is "
                               f"appended to the certificate file)")
        sec = d.Security(require_encryption=True, tls_ca_file=str(ca_file), tls_client_cert=str(cert),
                         **({"tls_client_key": str(key)} if key is not None else {}))
    else:
        names = _TLS_CONFIG
        sec = d.Security(require_encryption=True)  # every field from Dask's config
        if not (sec.tls_ca_file and sec.tls_client_cert):
            raise ClreconError(f"--cluster {address}: a tls:// scheduler needs certificates and none are given: "
                               f"{_TLS_HOWTO}")
    files = (sec.tls_ca_file, sec.tls_client_cert, sec.tls_client_key)
    what = ("CA certificate", "client certificate", "client key")
    for name, path, kind in zip(names, files, what, strict=True):
        if path is None or "\n" in str(path):  # absent key, or PEM text given in Dask's config itself
            continue
        try:
            with open(path, "rb") as fh:
                head = fh.read(64)
        except OSError as e:
            raise ClreconError(f"{name} {path}: cannot read the {kind} file ({e.strerror or e})") from None
        if b"-----BEGIN" not in head:
            raise ClreconError(f"{name} {path}: not a PEM file (expected a '-----BEGIN ...' line; the {kind} "
                               f"must be PEM-encoded, e.g. as openssl writes it)")
    ca = sec.tls_ca_file
    try:
        ssl.create_default_context(**({"cadata": ca} if "\n" in ca else {"cafile": ca}))
    except ssl.SSLError as e:
        raise ClreconError(f"{names[0]} {_short(ca)}: not a usable CA certificate ({e.reason or e})") from None
    try:
        sec.get_connection_args("client")  # builds the client's TLS context: certificate and key loaded
    except ssl.SSLError as e:
        key_part = f" / {names[2]} {_short(sec.tls_client_key)}" if sec.tls_client_key else ""
        raise ClreconError(f"{names[1]} {_short(sec.tls_client_cert)}{key_part}: not a PEM certificate with its "
                           f"matching private key ({e.reason or e})") from None
    return sec


def _short(value) -> str:
    """A file name as given, or ``<PEM text>`` for certificate text kept in Dask's config."""
    return "<PEM text>" if value is not None and "\n" in str(value) else str(value)


@contextlib.contextmanager
def connect(workers: int | None = None, cluster: str | None = None, device: str | None = None,
            security: Any = None) -> Iterator[Any]:
    """A ``distributed.Client``: a local cluster of ``workers`` processes, or the scheduler at ``cluster``.

    Local workers are single-threaded processes (OpenCL contexts cannot be forked or shared),
    with progress bars off and PoCL limited to this machine's cores divided among them (unless
    ``POCL_CPU_MAX_CU_COUNT`` is set). Everything started here is closed on exit.

    ``security``: a ``distributed.Security`` (:func:`tls_security`) for a ``tls://`` ``cluster``;
    a ``tls://`` address without one takes the certificates from Dask's config, and fails with
    a one-line error where that has none.
    """
    if workers is not None and cluster is not None:
        raise ClreconError("--workers and --cluster: give one of them (N local worker processes, or the address "
                           "of a running Dask scheduler)")
    if cluster is None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise ClreconError(f"--workers {workers!r}: expected a whole number of worker processes >= 1")
    if security is not None and not is_tls(cluster):
        where = f"--cluster {cluster}" if cluster is not None else f"--workers {workers}"
        raise ClreconError(f"{where}: TLS certificates ({', '.join(TLS_FLAGS)}) are for a tls:// scheduler address, "
                           f"e.g. --cluster tls://head:8786 (a --workers cluster talks over this machine's loopback)")
    d = dask_module()
    local = None
    if cluster is not None:
        if is_tls(cluster) and security is None:
            security = tls_security(address=cluster)
        try:
            client = d.Client(cluster, timeout="30s", security=security)
        except (OSError, TimeoutError, ValueError) as e:
            msg = str(e).splitlines()[0] if str(e) else type(e).__name__
            if is_tls(cluster):
                raise ClreconError(f"--cluster {cluster}: no TLS connection to a Dask scheduler there ({msg}); check "
                                   f"that one runs there and that its certificates and the client's are signed by "
                                   f"the CA of --tls-ca-file (docs/distributed.md)") from None
            raise ClreconError(f"--cluster {cluster}: no Dask scheduler answers there ({msg}); start one with "
                               f"`dask scheduler` or a SLURMCluster, and give a scheduler that requires TLS as "
                               f"tls://HOST:PORT with its certificates (docs/distributed.md)") from None
    else:
        cu = os.environ.get("POCL_CPU_MAX_CU_COUNT") or str(max(1, (os.cpu_count() or 1) // workers))
        local = d.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                               silence_logs=logging.ERROR,
                               env={"CLRECON_NO_PROGRESS": "1", "POCL_CPU_MAX_CU_COUNT": cu})
        client = d.Client(local)
    try:
        client.register_plugin(runtime_plugin(device))
        yield client
    finally:
        client.close()
        if local is not None:
            local.close()
