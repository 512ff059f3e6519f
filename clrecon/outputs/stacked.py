"""A run's reconstructions as one lazy 8-D :class:`xarray.DataArray` (``clrecon.open_run(path, stacked=True)``).

Layout (``docs/api.md``)::

    dims    method, pitch, variant, cardiac, resp, z, y, x
    coords  method   the run's reconstruction methods (str), in the order of its request
                     (``results.json`` ``request.methods``; others after, as volumes.h5 lists them)
            pitch    helical pitches (float); pitch_key ("p0.020") beside it on the same dim
            variant  "noisy", "noise-free" (those the run has; noisy first)
            cardiac, resp, z, y, x   as in the Dataset (clrecon.outputs.dataset), with their attrs
            stored, mae_hu_large, mae_hu_small, seconds   on (method, pitch, variant): whether the
                     run holds that reconstruction, its pooled MAE and its run seconds (NaN if absent)
    values  float32 HU; NaN for a (method, pitch, variant) the run does not hold
    attrs   those of the Dataset (run_dir, scene, has_cardiac, has_resp, format_version,
            results, metrics) and units = "HU"

It is a view of :func:`clrecon.outputs.dataset.open_dataset`: each (method, pitch, variant) is
that Dataset's lazy variable ``<method>_<pitch key>_<variant>``, read through its backend
array (:class:`clrecon.outputs.dataset.VolumeArray`, which reads volumes.h5 through
:func:`clrecon.outputs.volumes.read_part`), so nothing here knows the on-disk layout.

Laziness: :class:`StackedArray` is an :class:`xarray.backends.BackendArray` under xarray's
:class:`~xarray.core.indexing.LazilyIndexedArray`; opening reads only the axes and
``results.json``; a selection (``da.sel(method="local_linear", variant="noisy")``) stays
lazy until values are asked for, and then reads only the stored volumes and hyperslabs it
covers. The cardiac-blind ``r4dct`` (stored once per amplitude) and the phase-blind
``helical`` (stored once) are broadcast along the axes they do not vary on: their one stored
copy is read (once per volume asked for) and repeated only in the returned values; nothing
is copied on open. ``da.chunk(...)`` turns it into a dask array (if dask is installed).

Selecting a method: the array is a :class:`RunArray`, whose ``sel(method="local_linear")``
selects along the ``method`` dimension (xarray's own ``sel`` reads ``method=`` as its
inexact-lookup mode; here that mode is ``lookup=``). ``da.sel({"method": "local_linear"})``
and ``da.loc[{"method": "local_linear"}]`` work as in any xarray.

The ground truth and the phantom have no method, pitch or variant: they are not in the
stacked array but stay in the Dataset (``clrecon.open_run(path)["groundtruth"]``), whose
cardiac, resp, z, y, x coordinates are the same, so ``da - ds["groundtruth"]`` aligns.
"""

from __future__ import annotations

import numpy as np
import xarray as xr
from xarray.backends import BackendArray
from xarray.core import indexing

from clrecon.core import jsonio
from clrecon.core.errors import StoreError
from clrecon.outputs.dataset import open_dataset
from clrecon.outputs.volumes import DIMS

STACK_DIMS = ("method", "pitch", "variant") + DIMS
_VARIANT_ORDER = ("noisy", "noise-free")
_PER_VOLUME = ("mae_hu_large", "mae_hu_small", "seconds")


class StackedArray(BackendArray):
    """The reconstructions of a run as one lazily indexable 8-axis array (NaN where one is absent).

    ``volumes``: ``{(method_index, pitch_index, variant_index): xarray.Variable}``, each a lazy
    5-D variable on ``(cardiac, resp, z, y, x)`` of the shape ``shape[3:]``.
    """

    def __init__(self, volumes: dict, shape: tuple):
        self.volumes = volumes
        self.shape = tuple(shape)
        self.dtype = np.dtype(np.float32)

    def __getitem__(self, key: indexing.ExplicitIndexer) -> np.ndarray:
        return indexing.explicit_indexing_adapter(key, self.shape, indexing.IndexingSupport.BASIC, self._raw)

    def _raw(self, key: tuple) -> np.ndarray:
        """Basic (int / slice) selection on the 8 axes -> the stored volumes' hyperslabs, stacked."""
        picks = [range(n)[k] if isinstance(k, slice) else [int(k)] for n, k in zip(self.shape[:3], key[:3],
                                                                                     strict=True)]
        inner = tuple(len(range(n)[k]) for n, k in zip(self.shape[3:], key[3:], strict=True) if isinstance(k, slice))
        out = np.full(tuple(len(p) for p in picks) + inner, np.nan, self.dtype)
        if out.size:
            for a, i in enumerate(picks[0]):
                for b, j in enumerate(picks[1]):
                    for c, v in enumerate(picks[2]):
                        var = self.volumes.get((i, j, v))
                        if var is not None:
                            out[a, b, c] = np.asarray(var[key[3:]].values, self.dtype)
        drop = tuple(ax for ax, k in enumerate(key[:3]) if not isinstance(k, slice))
        return out.reshape(tuple(n for ax, n in enumerate(out.shape) if ax not in drop))


class RunArray(xr.DataArray):
    """An :class:`xarray.DataArray` whose ``sel(method=...)`` selects along a ``method`` dimension.

    xarray's own ``sel`` reads ``method=`` as its inexact-lookup mode (``"nearest"``, ``"pad"``,
    ...), so on a plain DataArray a dimension named ``method`` can only be selected as
    ``sel({"method": "local_linear"})`` or ``.loc[...]``. Here, while ``method`` is a dimension
    of the array, ``method=`` names the reconstruction method(s) and ``lookup=`` is xarray's
    lookup mode: ``da.sel(method="nearest", variant="noisy", cardiac=0.38, lookup="nearest")``.
    Labels (method, variant, pitch_key: string coordinates) are always matched exactly; the
    lookup mode applies to the numeric coordinates (pitch, cardiac, resp, z, y, x). Once the
    method dimension is gone (one method selected), ``method=`` is xarray's lookup mode again
    (``lookup=`` still works). Everything else is xarray's DataArray; operations keep this type.
    """

    __slots__ = ()

    def sel(self, indexers=None, method=None, tolerance=None, drop=False, lookup=None, **indexers_kwargs):
        if indexers is not None and indexers_kwargs:
            raise ValueError("cannot specify both keyword and positional arguments to .sel")
        wanted = dict(indexers if indexers is not None else indexers_kwargs)
        if method is not None and "method" in self.dims:
            wanted["method"] = method
        elif method is not None:
            if lookup is not None:
                raise TypeError(f"sel: method={method!r} and lookup={lookup!r}: give the lookup mode once")
            lookup = method
        if lookup is None:
            return xr.DataArray.sel(self, wanted, tolerance=tolerance, drop=drop)
        labels = {k: v for k, v in wanted.items() if k in self.indexes and self.indexes[k].dtype.kind in "OUS"}
        out = xr.DataArray.sel(self, labels, drop=drop) if labels else self
        rest = {k: v for k, v in wanted.items() if k not in labels}
        return xr.DataArray.sel(out, rest, method=lookup, tolerance=tolerance, drop=drop) if rest else out


def open_stacked(path) -> RunArray:
    """The run directory ``path`` as one lazy :class:`RunArray` (an ``xarray.DataArray``) on :data:`STACK_DIMS`.

    One-line :class:`~clrecon.core.errors.StoreError` for a missing or unreadable run, or a
    run without reconstructions. Close with ``da.close()`` (or ``with``).
    """
    ds = open_dataset(path)
    try:
        recons = [(name, var.attrs) for name, var in ds.data_vars.items() if var.attrs.get("kind") == "reconstruction"]
        if not recons:
            raise StoreError(f"{ds.attrs.get('run_dir', path)}: no reconstructions in this run directory to stack "
                             f"(it holds {', '.join(ds.data_vars) or 'no volumes'})")
        methods = list(dict.fromkeys(a["method"] for _, a in recons))
        requested = jsonio.loads(ds.attrs.get("results", "{}")).get("request", {}).get("methods") or []
        methods.sort(key=lambda m: requested.index(m) if m in requested else len(requested))  # stable
        pkeys = sorted({a["pitch_key"] for _, a in recons}, key=lambda k: float(k[1:]))
        variants = sorted({a["variant"] for _, a in recons},
                          key=lambda v: (_VARIANT_ORDER.index(v) if v in _VARIANT_ORDER else len(_VARIANT_ORDER), v))
        n3 = (len(methods), len(pkeys), len(variants))
        volumes = {}
        stored = np.zeros(n3, bool)
        per_volume = {k: np.full(n3, np.nan) for k in _PER_VOLUME}
        for name, a in recons:
            idx = (methods.index(a["method"]), pkeys.index(a["pitch_key"]), variants.index(a["variant"]))
            volumes[idx] = ds[name].variable
            stored[idx] = True
            for k in _PER_VOLUME:
                if k in a:
                    per_volume[k][idx] = float(a[k])
        three = STACK_DIMS[:3]
        coords = {
            "method": ("method", np.asarray(methods, dtype=object), {"long_name": "reconstruction method"}),
            "pitch": ("pitch", np.asarray([float(k[1:]) for k in pkeys]),
                      {"long_name": "helical pitch", "units": "1 (table feed per rotation / collimation)"}),
            "pitch_key": ("pitch", np.asarray(pkeys, dtype=object), {"long_name": "pitch key in volumes.h5"}),
            "variant": ("variant", np.asarray(variants, dtype=object), {"long_name": "noise variant"}),
            "stored": (three, stored, {"long_name": "the run holds this reconstruction (else NaN values)"}),
            "mae_hu_large": (three, per_volume["mae_hu_large"], {"long_name": "pooled MAE, large FOV", "units": "HU"}),
            "mae_hu_small": (three, per_volume["mae_hu_small"], {"long_name": "pooled MAE, small FOV", "units": "HU"}),
            "seconds": (three, per_volume["seconds"], {"long_name": "run seconds of the method", "units": "s"}),
        }
        for d in DIMS:
            coords[d] = ds[d].variable
        shape = n3 + tuple(ds.sizes[d] for d in DIMS)
        data = indexing.LazilyIndexedArray(StackedArray(volumes, shape))
        da = RunArray(xr.Variable(STACK_DIMS, data, {"units": "HU"}), coords=coords, name="recon")
        da.attrs.update({k: v for k, v in ds.attrs.items()})
        da.attrs["units"] = "HU"
    except BaseException:
        ds.close()
        raise
    da.set_close(ds.close)
    return da
