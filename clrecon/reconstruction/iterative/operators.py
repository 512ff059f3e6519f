"""The cone-beam system matrix of the iterative method, split into ordered subsets of views.

:class:`ConeOperator` is A: a voxel volume (1/mm) on a :class:`~clrecon.reconstruction.iterative.geometry.VolumeGrid`
to the line integrals of a list of views (the voxel projector, Joseph's weights), and its exact
transpose (the matched backprojector), for one *subset* of the views at a time. A subset is a
list of :class:`~clrecon.reconstruction.iterative.geometry.ViewGroup` slices; its data are the
views' projections ``(m, n_rows, n_cols)`` float32 in the order of the concatenated groups.

Ordered subsets (:func:`interleaved_subsets`): subset ``k`` of ``n`` holds every ``n``-th view
of the scan starting at ``k``, so each subset spans every gantry angle and the whole z range
(the classic choice for OS methods on helical data). The motion-compensated operator
(:mod:`clrecon.reconstruction.iterative.motion_operator`) subsets by motion state instead.
"""

from __future__ import annotations

import numpy as np

from clrecon.reconstruction.iterative.cone_backprojector import backproject_pair, backproject_volume
from clrecon.reconstruction.iterative.cone_gather import gather_backproject
from clrecon.simulation.voxel_projector import chord_lengths, project_volume


def interleaved_subsets(n_views: int, n_subsets: int) -> list[np.ndarray]:
    """Positions 0..n_views-1 dealt round-robin into ``n_subsets`` sorted index arrays."""
    if not (isinstance(n_subsets, (int, np.integer)) and 1 <= n_subsets <= max(1, n_views)):
        raise ValueError(f"n_subsets = {n_subsets!r}: must be an integer in [1, {max(1, n_views)}]")
    return [np.arange(k, n_views, n_subsets, dtype=np.int64) for k in range(int(n_subsets))]


def split_groups(groups, positions) -> list:
    """The parts of ``groups`` whose ``rows`` are among ``positions``: a list of ViewGroups (each a
    group's views among them, in the group's order; groups with none left out)."""
    positions = np.asarray(positions, np.int64)
    out = []
    for g in groups:
        sel = np.flatnonzero(np.isin(g.rows, positions))
        if sel.size:
            out.append(g.take(sel))
    return out


def project_groups(x, grid, parts, rt=None) -> np.ndarray:
    """A x over the views of ``parts`` (ViewGroups), concatenated: (m, n_rows, n_cols) float32."""
    outs = [project_volume(x, grid.origin_mm, grid.spacing_mm, *p.frames, p.cells[0], p.cells[1], rt=rt,
                           v_scale=p.cells[2]) for p in parts]
    return outs[0] if len(outs) == 1 else np.concatenate(outs, axis=0)


def chords_groups(grid, parts) -> np.ndarray:
    """A 1 over the views of ``parts`` (each ray's length in mm inside the grid's box), in the order of
    :func:`project_groups`, without projecting (:func:`~clrecon.simulation.voxel_projector.chord_lengths`):
    (m, n_rows, n_cols) float32; SART's row sums for a non-negative operator whose volume of ones
    reaches the projector as ones."""
    outs = [chord_lengths(grid.origin_mm, grid.spacing_mm, grid.shape, *p.frames, p.cells[0], p.cells[1],
                          v_scale=p.cells[2]) for p in parts]
    return outs[0] if len(outs) == 1 else np.concatenate(outs, axis=0)


#: SART's backprojectors: the projector's exact transpose, or the voxel-driven gather (about A^T).
BACKPROJECTORS = ("matched", "voxel")


def backproject_groups(proj, grid, parts, rt=None, proj2=None, kind: str = "matched"):
    """A^T proj over the views of ``parts`` in the order of :func:`project_groups`: (nz, ny, nx) float32
    (float64 sum over the groups, in their order). With ``proj2`` (same shape): the pair
    (A^T proj, A^T proj2) from one pass over the rays
    (:func:`~clrecon.reconstruction.iterative.cone_backprojector.backproject_pair`, each the same bits as a
    call of its own). ``kind = "voxel"``: the voxel-driven B ~ A^T instead
    (:func:`~clrecon.reconstruction.iterative.cone_gather.gather_backproject`, its pair likewise)."""
    if kind not in BACKPROJECTORS:
        raise ValueError(f"backprojector {kind!r}: must be one of {BACKPROJECTORS}")
    out, k = None, 0
    for p in parts:
        m = len(p.rows)
        geo = (grid.shape, grid.origin_mm, grid.spacing_mm, *p.frames, p.cells[0], p.cells[1])
        if kind == "voxel":
            b = gather_backproject(proj[k:k + m], *geo, rt=rt, v_scale=p.cells[2],
                                   proj2=None if proj2 is None else proj2[k:k + m])
            b = b if proj2 is not None else (b,)
        elif proj2 is None:
            b = (backproject_volume(proj[k:k + m], *geo, rt=rt, v_scale=p.cells[2]),)
        else:
            b = backproject_pair(proj[k:k + m], proj2[k:k + m], *geo, rt=rt, v_scale=p.cells[2])
        out = [x.astype(np.float64) for x in b] if out is None else [o + x for o, x in zip(out, b, strict=True)]
        k += m
    out = tuple(o.astype(np.float32) for o in out)
    return out[0] if proj2 is None else out


class ConeOperator:
    """A over ``groups`` (the views of one scan, :func:`~clrecon.reconstruction.iterative.geometry.view_groups`),
    on ``grid``, split into ``n_subsets`` interleaved subsets.

    ``subset_rows(s)`` gives the table positions of subset ``s`` in its data order;
    ``forward(x, s)`` (m_s, R, C) and ``adjoint(r, s)`` (nz, ny, nx) are A_s and A_s^T.
    """

    def __init__(self, grid, groups, n_subsets: int, rt=None):
        self.grid, self.rt = grid, rt
        n = sum(len(g.rows) for g in groups)
        self._parts = [split_groups(groups, pos) for pos in interleaved_subsets(n, n_subsets)]
        self.n_subsets = len(self._parts)
        self.unknown_shape = grid.shape

    def subset_rows(self, s: int) -> np.ndarray:
        return np.concatenate([p.rows for p in self._parts[s]])

    def forward(self, x, s: int) -> np.ndarray:
        return project_groups(x, self.grid, self._parts[s], self.rt)

    def adjoint(self, r, s: int) -> np.ndarray:
        return backproject_groups(r, self.grid, self._parts[s], self.rt)

    def row_sums(self, s: int) -> np.ndarray:
        """A_s 1 (SART's R_s): the rays' chords through the grid's box, without projecting."""
        return chords_groups(self.grid, self._parts[s])

    def direction_and_col_sums(self, r, w, s: int) -> tuple[np.ndarray, np.ndarray]:
        """(A_s^T r, A_s^T w) from one walk of the rays: SART's update and column sums at a subset's first visit."""
        return backproject_groups(r, self.grid, self._parts[s], self.rt, proj2=w)
