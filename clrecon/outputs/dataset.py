"""A run directory as a lazily loaded :class:`xarray.Dataset` (behind :func:`clrecon.open_run`).

Layout (``docs/api.md``)::

    dims       cardiac (n_c), resp (n_r), z (nz), y (ny), x (nx)
    coords     cardiac  target cardiac phases (fraction of the R-R interval)
               resp     target respiratory amplitudes (0 end-exhale .. 1 end-inhale)
               z, y, x  voxel centres, mm, DICOM patient frame (LPS)
    data_vars  <method>_<pitch key>_<variant>  e.g. local_linear_p0.020_noisy, nearest_p0.100_noise-free
               groundtruth, phantom
               all float32 HU on (cardiac, resp, z, y, x)
    attrs      run_dir, scene, has_cardiac, has_resp, format_version, and when results.json is
               there: results (the whole results.json) and metrics (its "metrics"), JSON strings

Every variable has all five dimensions. A scene without cardiac motion (or without breathing)
stores no such axis on disk (:mod:`clrecon.outputs.volumes`); here that dimension has length
1 (coordinate: the single target, cardiac phase 0 or the breath-hold / mid amplitude) and
``attrs["has_cardiac"]`` (``has_resp``) is 0.

Laziness: each variable is an :class:`xarray.core.indexing.LazilyIndexedArray` over a
:class:`xarray.backends.BackendArray` (:class:`VolumeArray`) that reads the HDF5 hyperslab a
selection needs, when its values are asked for. Opening reads only the axes and attributes;
``ds["groundtruth"].sel(cardiac=0.4, resp=0.25, method="nearest").values`` reads one target.
No dask. ``ds.close()`` (or ``with``) closes the file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import xarray as xr
from xarray.backends import BackendArray
from xarray.core import indexing

from clrecon.core import jsonio
from clrecon.core.errors import StoreError
from clrecon.outputs.rundir import RunDirectory, Source
from clrecon.outputs.volumes import DIMS, FORMAT_VERSION, read_part

_COORD_ATTRS = {
    "cardiac": {"long_name": "cardiac phase of the target", "units": "fraction of the R-R interval"},
    "resp": {"long_name": "respiratory amplitude of the target", "units": "1 (0 end-exhale, 1 end-inhale)"},
    "z": {"long_name": "z of the voxel centre (LPS, superior +)", "units": "mm"},
    "y": {"long_name": "y of the voxel centre (LPS, posterior +)", "units": "mm"},
    "x": {"long_name": "x of the voxel centre (LPS, patient left +)", "units": "mm"},
}
_AXIS_OF = dict(zip(DIMS, ("cardiac_phase", "resp_amplitude", "z_mm", "y_mm", "x_mm"), strict=True))


class VolumeArray(BackendArray):
    """One 5D volume of a run as a lazily indexable 5-axis array (length-1 axes restored)."""

    def __init__(self, run: RunDirectory, dataset: str):
        ds = run.h5[dataset]
        self.run = run
        self.dataset = dataset
        self.disk_dims = tuple(str(d) for d in ds.attrs["dims"])
        bc = {str(d) for d in ds.attrs.get("broadcast", [])}
        self.shape = run.shape
        self.dtype = np.dtype(np.float32)  # float16 on disk is read as float32
        want = tuple(1 if d in bc else n for d, n in zip(DIMS, self.shape, strict=True) if d in self.disk_dims)
        if tuple(ds.shape) != want or not set(self.disk_dims) <= set(DIMS):
            raise StoreError(f"{run.dir}: volume {dataset} has shape {tuple(ds.shape)} on axes "
                             f"{list(self.disk_dims)}, not that of the run's axes {self.shape}")

    def __getitem__(self, key: indexing.ExplicitIndexer) -> np.ndarray:
        return indexing.explicit_indexing_adapter(key, self.shape, indexing.IndexingSupport.BASIC, self._raw)

    def _raw(self, key: tuple) -> np.ndarray:
        """Basic (int / slice) selection on the 5 axes -> the HDF5 hyperslab, reshaped."""
        out_shape = tuple(len(range(n)[k]) for n, k in zip(self.shape, key, strict=True) if isinstance(k, slice))
        if 0 in out_shape:
            return np.empty(out_shape, self.dtype)
        # absent axes have length 1; broadcast ones are restored by read_part
        return read_part(self.run.h5, self.dataset, dict(zip(DIMS, key, strict=True))).reshape(out_shape)


def _variable_attrs(run: RunDirectory, src: Source) -> dict:
    attrs: dict = {"method": src.method, "units": "HU", "dataset": src.dataset}
    if src.pitch_key is None:
        attrs["kind"] = "reference"
        return attrs
    attrs.update(kind="reconstruction", pitch=src.pitch, pitch_key=src.pitch_key, variant=src.variant)
    if run.has_results:
        res = run.results
        met = res.get("metrics", {}).get(src.pitch_key, {}).get(src.variant, {}).get(src.method)
        if met:
            for fov in ("large", "small"):
                if fov in met and "mae_hu" in met[fov]:
                    attrs[f"mae_hu_{fov}"] = float(met[fov]["mae_hu"])
        secs = res.get("method_seconds", {}).get(src.pitch_key, {}).get(src.variant, {}).get(src.method)
        if secs is not None:
            attrs["seconds"] = float(secs)
    return attrs


def _json(obj) -> str:
    """Strict JSON (non-finite values as null, listed with their reason: :mod:`clrecon.core.jsonio`)."""
    return jsonio.dumps(obj)


def open_dataset(path) -> xr.Dataset:
    """The run directory ``path`` (or its ``volumes.h5``) as a lazy :class:`xarray.Dataset`.

    One-line :class:`~clrecon.core.errors.StoreError` for a missing or unreadable run.
    """
    run = RunDirectory(path)
    try:
        ax = run.axes
        coords = {d: xr.Variable(d, np.asarray(ax[_AXIS_OF[d]], np.float64), _COORD_ATTRS[d]) for d in DIMS}
        data_vars = {}
        disk_dims: tuple = ()
        for src in run.sources:
            arr = VolumeArray(run, src.dataset)
            disk_dims = disk_dims or arr.disk_dims
            data_vars[src.name] = xr.Variable(DIMS, indexing.LazilyIndexedArray(arr), _variable_attrs(run, src))
        attrs: dict = {"run_dir": str(Path(run.dir).resolve()),
                       "format_version": int(run.h5.attrs.get("format_version", FORMAT_VERSION))}
        dims_known = {}
        if run.has_results:
            res = run.results
            attrs["scene"] = str(res.get("scene", {}).get("name", ""))
            dims_known = res.get("dimensions", {}) or {}
            attrs["results"] = _json(res)
            attrs["metrics"] = _json(res.get("metrics", {}))
        for d, key in (("cardiac", "has_cardiac"), ("resp", "has_resp")):
            if d in dims_known:
                attrs[key] = int(bool(dims_known[d]))
            elif disk_dims:
                attrs[key] = int(d in disk_dims)
            else:
                attrs[key] = int(len(ax[_AXIS_OF[d]]) > 1)
        ds = xr.Dataset(data_vars, coords=coords, attrs=attrs)
    except BaseException:
        run.close()
        raise
    ds.set_close(run.close)
    return ds
