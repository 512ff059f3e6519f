"""Scale a run out on Dask: compute its missing units on the workers, then finish as usual.

``clrecon run --workers N`` (a local cluster of N single-threaded worker processes) or
``--cluster ADDRESS`` (an existing scheduler; docs/distributed.md has the SLURM recipe), and
``clrecon.run(..., client=...)`` in Python. :func:`compute_units` runs before the
single-process path of :func:`clrecon.pipeline.run.run`; it

1. plans each pitch exactly as the serial path does (the same slices still to do, the same
   plan, the same slab decomposition);
2. sends the units (:mod:`clrecon.pipeline.work_units`) to the workers: projection chunks
   first, then each pitch's reconstruction slabs once its store is assembled, and the
   truth targets in between; the workers return NumPy arrays;
3. writes each result, as it arrives, with the run's own writers (the projection store's
   unit files, :class:`clrecon.outputs.volumes.VolumeWriter`'s unit files): atomic,
   checksummed, the same files the serial path writes.

The serial path then finds every unit done and only assembles, evaluates and reports, so
volumes and metrics are bit-identical to a single-process run. A worker killed mid-unit
costs only that unit (Dask gives it to another worker; nothing was written); a client
killed or interrupted keeps every unit written so far, and the rerun computes only the rest.

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
import time
import uuid
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from clrecon.core.errors import ClreconError
from clrecon.evaluation import groundtruth
from clrecon.evaluation.truth_cache import TruthCache, truth_key
from clrecon.outputs.volumes import VolumeWriter, pitch_key
from clrecon.pipeline import slabs as slabs_mod
from clrecon.pipeline import work_units
from clrecon.reconstruction import reconstruct
from clrecon.simulation.simulate import CHUNK
from clrecon.simulation.store import ProjectionStore

INSTALL_HINT = "pip install 'clrecon[dask]' (dask[distributed] >= 2024.1)"
#: Task priorities: projections gate the reconstruction, truths fill the gaps.
_PRIORITY = {"simulate": 20, "reconstruct": 10, "truth": 0}


def _dask():
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
    d = _dask()
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
    d = _dask()
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


# ----------------------------------------------------------------------------------------
# the distributed phase of a run
@dataclass
class Records:
    """What the distributed phase did, in the shapes ``results.json`` keeps (see :func:`merge_records`)."""

    sim_info: dict = field(default_factory=dict)
    diagnostics: dict = field(default_factory=dict)
    sampling: dict = field(default_factory=dict)
    method_seconds: dict = field(default_factory=dict)
    method_plan_seconds: dict = field(default_factory=dict)
    stage_seconds: dict = field(default_factory=dict)
    projection_units: int = 0
    summary: dict = field(default_factory=dict)

    def add(self, stage: str, seconds: float) -> None:
        self.stage_seconds[stage] = self.stage_seconds.get(stage, 0.0) + seconds


@dataclass
class _Pitch:
    """One pitch in flight: its store (being written while chunks arrive), plan and slabs."""

    pitch: float
    store: ProjectionStore
    plans: list  # per slab: its plan, or None (over the plan budget: the worker plans it)
    methods: tuple
    todo: np.ndarray
    slabs: list
    chunks_left: int = 0
    writing: contextlib.ExitStack | None = None
    times: reconstruct.StageTimes = field(default_factory=reconstruct.StageTimes)


def compute_units(client, writer: VolumeWriter, scene, cfg, *, methods, pitches, variants, targets,
                  slices_z: np.ndarray, full_shape: tuple, cache_dir, progress: bool = True,
                  log: Callable[..., Any] = print) -> Records:
    """Compute every unit of the run that ``writer`` and the stores lack, on ``client``'s workers.

    ``writer`` is the run's :class:`VolumeWriter` (its datasets are declared here as ``run``
    declares them); ``cfg`` the run's :class:`~clrecon.reconstruction.reconstruct.ReconstructionConfig`;
    ``cache_dir`` the resolved projection store folder. Returns the :class:`Records` for
    ``results.json``. Raises :class:`ClreconError` naming the unit that failed; the units
    written before stay for the rerun.
    """
    d = _dask()
    t_start = time.perf_counter()
    info = client.scheduler_info().get("workers", {})
    threaded = [w for w, i in info.items() if i.get("nthreads", 1) > 1]
    if threaded:
        raise ClreconError(f"client: worker {threaded[0]} runs {info[threaded[0]]['nthreads']} threads; clrecon needs "
                           f"single-threaded worker processes (one OpenCL queue each): start them with "
                           f"threads_per_worker=1 / --nthreads 1 (docs/distributed.md)")
    client.register_plugin(runtime_plugin())  # idempotent: kept if connect() registered one (with its device)
    nw = len(info)
    ph = _Phase(client=client, jobs=_Jobs(client, d, progress, nw), writer=writer, scene=scene, cfg=cfg,
                targets=targets, variants=tuple(variants), cache_dir=str(cache_dir), progress=progress,
                slices_z=np.asarray(slices_z))
    try:
        for pitch in pitches:
            ph.start_pitch(pitch, methods, slices_z, full_shape)
        ph.start_truths(slices_z, full_shape)
        if ph.jobs.total:
            log(f"distributed: {ph.jobs.total} units on {nw} workers")
        ph.jobs.run()
        for pk, st in ph.states.items():
            _method_seconds(ph.rec, pk, st.times)
    except BaseException as e:
        ph.jobs.cancel()
        for st in ph.states.values():
            if st.writing is not None:  # the finished chunks stay as unit files for the rerun
                st.writing.__exit__(type(e), e, e.__traceback__)
        raise
    finally:
        for st in ph.states.values():
            st.store.close()
    jobs = ph.jobs
    ph.rec.summary = {
        "workers": nw, "scheduler": str(getattr(client.scheduler, "address", "")),
        "encrypted": is_tls(str(getattr(client.scheduler, "address", ""))), "units": dict(jobs.count),
        "wall_seconds": round(time.perf_counter() - t_start, 3),
        "unit_seconds": {k: {"sum": round(float(np.sum(v)), 3), "median": round(float(np.median(v)), 4)}
                         for k, v in jobs.unit_seconds.items() if v}}
    return ph.rec


@dataclass
class _Phase:
    """The distributed phase of one run: submits the units and writes their results as they arrive."""

    client: Any
    jobs: _Jobs
    writer: VolumeWriter
    scene: Any
    cfg: Any
    targets: Any
    variants: tuple
    cache_dir: str
    progress: bool = True
    slices_z: np.ndarray | None = None
    truths: TruthCache | None = None
    rec: Records = field(default_factory=Records)
    states: dict = field(default_factory=dict)

    def start_pitch(self, pitch: float, methods, slices_z: np.ndarray, full_shape: tuple) -> None:
        """Plan the pitch as ``run`` does and send out its missing projection chunks (or its slabs)."""
        pk, scene, cfg, rec = pitch_key(pitch), self.scene, self.cfg, self.rec
        slabs_mod.declare_recon(self.writer, pk, methods, self.variants, full_shape, len(slices_z))
        run_methods, todo = slabs_mod.unfinished(self.writer, pk, self.variants, methods)
        if todo.size == 0:
            return
        pp = slabs_mod.plan_pitch(scene, cfg, pitch, slices_z, todo, self.targets, run_methods, len(self.variants),
                                  self.progress)
        table, slabs, plans, needed = pp.table, pp.slabs, pp.plans, pp.needed
        rec.add("signals", pp.signals_seconds)
        rec.add("plan", pp.plan_seconds)
        rec.diagnostics[pk] = pp.diagnostics
        rec.sampling[pk] = pp.sampling
        rec.method_plan_seconds[pk] = dict(pp.method_plan_seconds)
        store = ProjectionStore.open(scene, pitch, cache_dir=self.cache_dir, table=table)
        missing = np.flatnonzero(needed & ~store.present)
        rec.sim_info[pk] = {"projections_total": len(table), "projections_needed": int(needed.sum()),
                            "projections_simulated": int(missing.size),
                            "projections_reused": int(np.count_nonzero(needed & store.present)),
                            "store": str(store.path)}
        st = self.states[pk] = _Pitch(pitch=pitch, store=store, plans=plans, methods=run_methods, todo=todo,
                                      slabs=slabs)
        self.jobs.expect(len(st.slabs) + -(-missing.size // CHUNK))
        if missing.size or store.state != "final":
            st.writing = contextlib.ExitStack()
            st.writing.enter_context(store.writing())
        for lo in range(0, missing.size, CHUNK):  # the chunks simulate() would project
            idx = missing[lo:lo + CHUNK]
            st.chunks_left += 1
            self.jobs.submit("simulate", f"projections {idx[0]}..{idx[-1]} of pitch {pitch:g}",
                             work_units.simulate_chunk, (scene, pitch, idx),
                             lambda res, st=st, idx=idx: self.on_chunk(st, idx, res))
        if st.chunks_left == 0:
            self.store_ready(st)

    def on_chunk(self, st: _Pitch, idx: np.ndarray, res) -> float:
        data, seconds = res
        t0 = time.perf_counter()
        st.store.write(idx, data)
        self.rec.add("simulate", seconds + time.perf_counter() - t0)
        self.rec.projection_units += 1
        st.chunks_left -= 1
        if st.chunks_left == 0:
            self.store_ready(st)
        return seconds

    def store_ready(self, st: _Pitch) -> None:
        """The pitch's projections are all in: assemble its store, then send its slabs out."""
        if st.writing is not None:
            st.writing.close()  # assembles <hash>.h5 and removes its unit files
            st.writing = None
        st.store.close()
        for k, (a, b) in enumerate(st.slabs):
            z = st.todo[a:b]
            plan, st.plans[k] = st.plans[k], None
            self.jobs.submit("reconstruct", f"reconstruction slab of slices {z[0]}..{z[-1]} at pitch {st.pitch:g}",
                             work_units.reconstruct_slab,
                             (self.cfg, self.scene, st.pitch, self.cache_dir, plan, self.slices_z[z], self.targets,
                              st.methods, self.variants),
                             lambda res, st=st, z=z: self.on_slab(st, z, res))

    def on_slab(self, st: _Pitch, z: np.ndarray, res) -> float:
        vols, seconds = res
        pk = pitch_key(st.pitch)
        for key, sec in seconds.items():
            st.times.add(key, sec)
        for (v, m), vol in vols.items():  # r4dct (1, n_r), helical (1, 1): stored as they are (as run() writes)
            self.writer.write(f"recon/{pk}/{v}/{m}", vol, z)
        return sum(sec for key, sec in seconds.items() if ":" not in key)

    def start_truths(self, slices_z: np.ndarray, full_shape: tuple) -> None:
        gt_cfg = groundtruth.GroundTruthConfig.from_scene(self.scene)
        n_c, n_r = self.targets.shape
        self.truths = TruthCache(self.cache_dir, truth_key(self.scene, slices_z, self.targets))
        slabs_mod.declare_truths(self.writer, full_shape, n_c * n_r, self.truths)
        for k in range(n_c * n_r):
            which = tuple(n for n in ("groundtruth", "phantom") if not self.writer.done(n)[k])
            if which:
                self.jobs.expect(1)
                self.jobs.submit("truth", f"truth of target {k} ({', '.join(which)})", work_units.truth_target,
                                 (gt_cfg, slices_z, self.targets, k, which),
                                 lambda res, k=k: self.on_truth(k, res))

    def on_truth(self, k: int, res) -> float:
        vols, seconds = res
        n_r = self.targets.shape[1]
        i, j = divmod(k, n_r)
        for name, vol in vols.items():
            self.truths.put(self.writer.write_target(name, i, j, n_r, vol))
        for stage, sec in seconds.items():
            self.rec.add(stage, sec)
        return sum(seconds.values())


def _method_seconds(rec: Records, pk: str, ptimes: reconstruct.StageTimes) -> None:
    """Per-method seconds and stage seconds of a pitch's slabs, booked as ``run`` books them."""
    plan_s = rec.method_plan_seconds.get(pk, {})
    for key, sec in ptimes.seconds.items():
        if key.startswith("plan:"):
            m = key.split(":", 1)[1]
            plan_s[m] = plan_s.get(m, 0.0) + sec
    rec.method_plan_seconds[pk] = {m: round(sec, 3) for m, sec in plan_s.items()}
    rec.method_seconds[pk] = {}
    for key, sec in ptimes.seconds.items():
        if key.startswith("method:"):
            _, m, v = key.split(":")
            rec.method_seconds[pk].setdefault(v, {})[m] = round(sec + plan_s.get(m, 0.0), 3)
        elif not key.startswith("plan:"):
            rec.add(key, sec)


def merge_records(rec: Records, times, sim_info: dict, method_seconds: dict, method_plan_seconds: dict,
                  diagnostics: dict, sampling: dict, units_written: dict) -> None:
    """Put the distributed phase's records into ``run``'s (in place): what the workers computed.

    Stage seconds are summed over the workers (compute seconds, not wall time: that is
    ``results["distributed"]["wall_seconds"]``).
    """
    for stage, sec in rec.stage_seconds.items():
        times.add(stage, sec)
    sim_info.update(rec.sim_info)
    method_seconds.update(rec.method_seconds)
    method_plan_seconds.update(rec.method_plan_seconds)
    diagnostics.update(rec.diagnostics)
    sampling.update(rec.sampling)
    units_written["projections"] = units_written.get("projections", 0) + rec.projection_units


class _Jobs:
    """Futures in flight, a progress bar with ETA over the units, and the first error as a ClreconError."""

    def __init__(self, client, d, progress: bool, nw: int):
        from tqdm import tqdm

        self.client, self.d = client, d
        self.pending: dict = {}
        self.total = 0
        self.count = {"simulate": 0, "reconstruct": 0, "truth": 0}
        self.unit_seconds: dict = {"simulate": [], "reconstruct": [], "truth": []}
        self.ac = d.as_completed()
        disable = (not progress) or os.environ.get("CLRECON_NO_PROGRESS") == "1"
        self.bar = tqdm(total=0, desc=f"units on {nw} workers", unit="unit", disable=disable, leave=False,
                        dynamic_ncols=True)

    def expect(self, n: int) -> None:
        self.total += n
        self.bar.total = self.total
        self.bar.refresh()

    def submit(self, kind: str, label: str, fn, args: tuple, on_done) -> None:
        key = f"clrecon-{kind}-{uuid.uuid4().hex[:12]}"
        with warnings.catch_warnings():
            # a slab's plan (its weights, MBs at paper scale) travels with its task on purpose: a
            # scattered copy would be lost with the worker holding it, and the unit with it
            warnings.filterwarnings("ignore", message="Sending large graph", category=UserWarning)
            fut = self.client.submit(fn, *args, key=key, pure=False, priority=_PRIORITY[kind])
        self.pending[fut.key] = (kind, label, on_done)
        self.ac.add(fut)

    def run(self) -> None:
        """Handle results as they complete (each callback may submit more) until none is left."""
        for fut in self.ac:
            kind, label, on_done = self.pending.pop(fut.key)
            try:
                res = fut.result()
            except self.d.KilledWorker as e:
                raise ClreconError(f"{label}: the workers computing it died (Dask gave up after its allowed "
                                   f"failures: {str(e).splitlines()[0]}); the finished units are kept: run the same "
                                   f"command again to resume") from None
            except ClreconError as e:
                raise ClreconError(f"{label}: {e}; the finished units are kept") from None
            except Exception as e:  # noqa: BLE001 - any failure of a unit on a worker is reported naming the unit
                msg = str(e).splitlines()[0] if str(e) else ""
                raise ClreconError(f"{label} failed on a worker ({type(e).__name__}: {msg}); the finished units "
                                   f"are kept: run the same command again to resume") from None
            finally:
                fut.release()
            self.unit_seconds[kind].append(float(on_done(res)))
            self.count[kind] += 1
            self.bar.update(1)
        self.bar.close()

    def cancel(self) -> None:
        self.bar.close()
        futs = list(self.ac.futures) if hasattr(self.ac, "futures") else []
        if futs:
            with contextlib.suppress(Exception):
                self.client.cancel(futs)
        self.pending.clear()
