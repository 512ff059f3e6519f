"""The run directory's volume store, ``volumes.h5`` (written by ``run``, read by report/viewer/export).

Layout (HDF5)::

    /axes/cardiac_phase  (n_c,)   target cardiac phases        (absent axis: length 1)
    /axes/resp_amplitude (n_r,)   target respiratory amplitudes
    /axes/z_mm (nz,) /axes/y_mm (ny,) /axes/x_mm (nx,)   voxel centres, LPS, mm
    /groundtruth                  ground-truth CT (exact in-plane projections + same FBP)
    /phantom                      voxelised analytic phantom
    /recon/<pitch>/<variant>/<method>     e.g. /recon/p0.020/noise-free/local_linear

Every volume dataset is float32 HU with attribute ``dims``: the axis names of its shape, a
subset of ``("cardiac", "resp", "z", "y", "x")`` — a scene without cardiac motion has no
cardiac axis on disk (its 5D volume is 4D), one without breathing no respiratory axis.
:func:`read_volume` always returns the full 5-axis array (size-1 axes restored).
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from clrecon.core.errors import StoreError

DIMS = ("cardiac", "resp", "z", "y", "x")
FORMAT_VERSION = 1


def pitch_key(pitch: float) -> str:
    return f"p{pitch:.3f}"


class VolumeWriter:
    """Writes ``volumes.h5`` as ``volumes.h5.partial`` and renames it when closed cleanly.

    Resumable: every finished block is marked in a ``done`` attribute (slices for
    reconstructions, targets for truths) after it is written and flushed. A later run with
    the same ``run_key`` (hash of scene and request) reopens the partial file and skips what
    is marked; any other key starts afresh.
    """

    def __init__(self, path: Path, axes: dict, keep_cardiac: bool, keep_resp: bool, run_key: str = ""):
        self.path = Path(path)
        self.partial = self.path.with_name(self.path.name + ".partial")
        self.keep = (keep_cardiac, keep_resp)
        self.resumed = False
        if self.partial.exists():
            try:
                f = h5py.File(self.partial, "a")
                if f.attrs.get("run_key") == run_key and f.attrs.get("format_version") == FORMAT_VERSION:
                    self.f, self.resumed = f, True
                else:
                    f.close()
            except OSError:  # a partial file too damaged to open: start again
                pass
        if not self.resumed:
            self.f = h5py.File(self.partial, "w")
            self.f.attrs["format_version"] = FORMAT_VERSION
            self.f.attrs["run_key"] = run_key
            for k, v in axes.items():
                self.f[f"axes/{k}"] = np.asarray(v, np.float64)

    def _dims(self):
        return tuple(d for d, keep in zip(DIMS, self.keep + (True, True, True), strict=True) if keep)

    def _squeeze(self, vol: np.ndarray) -> np.ndarray:
        drop = tuple(i for i, keep in enumerate(self.keep) if not keep)
        return vol.reshape(tuple(s for i, s in enumerate(vol.shape) if i not in drop))

    def create(self, name: str, full_shape: tuple, done_size: int) -> None:
        """Create dataset ``name`` (kept as it is when resuming) with a ``done`` mask of ``done_size``."""
        if name in self.f:
            return
        shape = self._squeeze(np.empty(full_shape, np.bool_)).shape
        chunks = tuple(1 for _ in shape[:-3]) + (1,) + tuple(shape[-2:])
        ds = self.f.create_dataset(name, shape=shape, dtype=np.float32, chunks=chunks)
        ds.attrs["dims"] = list(self._dims())
        ds.attrs["units"] = "HU"
        ds.attrs["done"] = np.zeros(done_size, np.uint8)

    def done(self, name: str) -> np.ndarray:
        """Boolean mask of the finished blocks of ``name`` (slices or flattened targets)."""
        return np.asarray(self.f[name].attrs["done"], bool)

    def _mark(self, name: str, which) -> None:
        self.f.flush()  # data first, then the mark: a crash between them only redoes work
        d = np.asarray(self.f[name].attrs["done"], np.uint8)
        d[which] = 1
        self.f[name].attrs["done"] = d
        self.f.flush()

    def write(self, name: str, vol: np.ndarray, z_index) -> None:
        """Write a full-axis block ``(n_c, n_r, s, ny, nx)`` into slice indices ``z_index`` (increasing)."""
        v = self._squeeze(vol)
        z = np.asarray(z_index)
        self.f[name][(slice(None),) * (v.ndim - 3) + (list(z),)] = v
        self._mark(name, z)

    def write_target(self, name: str, i: int, j: int, n_resp: int, vol: np.ndarray) -> None:
        """Write one target's ``(nz, ny, nx)`` volume at cardiac index ``i``, respiratory index ``j``."""
        sel = tuple(k for k, keep in zip((i, j), self.keep, strict=True) if keep)
        self.f[name][sel] = vol
        self._mark(name, i * n_resp + j)

    def close(self) -> None:
        self.f.close()
        self.partial.replace(self.path)

    def abort(self) -> None:
        try:
            self.f.close()
        except Exception:  # noqa: BLE001 - best-effort cleanup on a failing run: the original error matters
            pass


def open_volumes(path) -> h5py.File:
    """Open a run's ``volumes.h5`` read-only, with one-line errors for missing/old/corrupt files."""
    p = Path(path)
    if p.is_dir():
        p = p / "volumes.h5"
    if not p.exists():
        raise StoreError(f"{p}: no volumes in this run directory (was `clrecon run` finished?)")
    try:
        f = h5py.File(p, "r")
    except OSError as e:
        raise StoreError(f"{p}: not a readable HDF5 file ({e})") from None
    version = f.attrs.get("format_version")
    if version != FORMAT_VERSION:
        f.close()
        raise StoreError(f"{p}: volume format {version!r} is not {FORMAT_VERSION}; "
                         f"re-run `clrecon run` with this version")
    return f


def read_volume(f: h5py.File, name: str, index=None) -> np.ndarray:
    """A volume as a full 5-axis array ``(n_c, n_r, nz, ny, nx)``.

    ``index`` optionally picks (cardiac_index, resp_index) and returns ``(nz, ny, nx)``.
    """
    ds = f[name]
    dims = list(ds.attrs["dims"])
    if index is not None:
        sel = []
        for d in dims:
            if d == "cardiac":
                sel.append(index[0])
            elif d == "resp":
                sel.append(index[1])
            else:
                sel.append(slice(None))
        return ds[tuple(sel)]
    arr = ds[()]
    shape = [arr.shape[dims.index(d)] if d in dims else 1 for d in DIMS]
    return arr.reshape(shape)


def list_recons(f: h5py.File) -> list[tuple[str, str, str]]:
    """(pitch_key, variant, method) of every reconstruction in the file."""
    out = []
    if "recon" not in f:
        return out
    for p in f["recon"]:
        for v in f["recon"][p]:
            for m in f["recon"][p][v]:
                out.append((p, v, m))
    return out
