"""What an interpolation method is: the :class:`Method` record every method module registers.

A method turns, for each (slice, view) group and each target (c*, a*), the group's candidate
points (c_k, a_k) into at most ``neighbours`` (index, weight) slots. Its ``weights`` function
sees one padded chunk of groups (:class:`Chunk`), the targets, the signed differences to the
targets and the options (:class:`Options`), and returns local ``(g, T, K)`` indices into the
chunk's candidates and float64 weights; :func:`clrecon.reconstruction.interpolation.weights.batch_weights`
does the validation, chunking, deltas, flat indexing and padding around it.

Everything a user sees about the methods -- the scene check, CLI help, report and export order,
figure order and markers, which methods are 5DCT, which are solved on the respiratory-only
target grid -- is read from these records (:mod:`clrecon.reconstruction.interpolation.registry`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

#: ``target_grid`` values: every (cardiac, amplitude) target, one cardiac-blind target per
#: amplitude (the method ignores c*; the volume is the same for every cardiac phase), or one
#: phase-blind target (the method ignores c* and a*; one volume stands for every target).
TARGET_GRIDS = ("5d", "resp", "none")
#: ``axes`` values: the phase-space axes a method uses.
AXES = ("cardiac", "resp")


@dataclass
class Chunk:
    """Groups g0..g1 padded to (g, N); candidates first, ``valid`` marks them.

    ``c``, ``a`` (g, N) cardiac phase and amplitude (0 in padding); ``dz`` (g, N) the
    candidate's z distance |z_slice - z_k| in mm (inf in padding), or None when the caller
    gave no ``dz`` to ``batch_weights``; ``counts`` (g,) candidates per group; ``start`` (g,)
    flat offset of each group's first candidate.
    """

    c: np.ndarray
    a: np.ndarray
    valid: np.ndarray
    counts: np.ndarray
    start: np.ndarray  # flat offset of each group's first candidate
    dz: np.ndarray | None = None


@dataclass(frozen=True)
class Options:
    """The keyword options of ``batch_weights`` a method may read (see its docstring)."""

    kappa: float = 1.0
    sigma: float = 0.15
    cardiac_bin_width: float = 0.2
    resp_bin_width: float = 0.1
    use_cardiac: bool = True
    use_resp: bool = True
    workers: int = 1
    rt: Any = None
    precision: str | None = None
    extrapolate: bool = False
    local_linear_points: str = "quadrants"
    local_linear_count: int = 2
    #: factor s of the cardiac axis in the phase-space distance and barycentric's triangulation
    cardiac_distance_scale: float = 1.0
    #: ``cv_tuned``: the chosen fixed kernel ``(method, ((knob, value), ...))``, or None
    tuned: tuple | None = None


#: ``weights(ch, targets, dc, da, d2, opts) -> (index (g, T, K) int, weight (g, T, K) float64)``:
#: ``targets`` (T, 2) with c in [0, 1); ``dc``, ``da``, ``d2`` (g, T, N) signed circular cardiac
#: difference, amplitude difference and squared distance (inf for padding), with dc = 0 where
#: the cardiac axis is off and da = 0 where the respiratory axis is off. A method may return a
#: third element, ``branch`` (g, T) int8, the branch each (group, target) took (diagnostics:
#: ``Weights.branch``; barycentric reports triangle / segment / nearest).
WeightsFn = Callable[[Chunk, np.ndarray, np.ndarray, np.ndarray, np.ndarray, Options], tuple]


@dataclass(frozen=True)
class Method:
    """One interpolation method.

    Attributes
    ----------
    name : str
        Registry key, ``recon.methods`` entry, volume-file dataset name.
    label : str
        Human name in figures (e.g. ``"r4DCT"``).
    neighbours : int or None
        K, the slots per (slice, view, target); None: varies with the data (``bin``: the
        largest bin count).
    target_grid : str
        ``"5d"``: solved for every (c*, a*) target; ``"resp"``: one cardiac-blind target per
        amplitude (the reconstruction broadcasts it over the cardiac targets); ``"none"``: one
        phase-blind target (broadcast over every (c*, a*) target).
    axes : tuple of str
        Phase-space axes the method uses (``"cardiac"``, ``"resp"``); the cardiac difference
        is not computed for a method without ``"cardiac"``. Empty only for a ``"none"`` grid
        (a phase-blind method, e.g. ``helical``, which sees the candidates' ``dz`` instead).
    five_d : bool
        A 5DCT method (interpolates in both axes; compared with r4DCT in the
        respiratory-only study and drawn in the phase-space figure).
    marker : str
        Matplotlib marker in the error-vs-time figure.
    rank : int
        Best first: order of the report tables and of the export default (lowest rank
        present wins); figures show the methods the other way round, simplest first.
    weights : WeightsFn
        The method itself (see :data:`WeightsFn`).
    opt_in : bool
        Not in the ``recon.methods`` default (:func:`~clrecon.reconstruction.interpolation.registry.default_methods`):
        run only when a scene or ``--methods`` names it (``cv_tuned``).
    stage : str or None
        The pipeline stage that makes its volumes from the first pass, when it is not the
        ``reconstruct`` stage (``mc``: ``mc_reconstruct``); ``reconstruct`` plans and skips it.
    first_pass : str or None
        For a method with a ``stage``: the method whose volumes it is made from (``mc``:
        ``barycentric``). A registered 5-D method, registered before it
        (:func:`~clrecon.reconstruction.interpolation.registry.register_method` checks); every
        place that needs the first pass (the run's request check, the plan, the ``mc`` stage,
        the truth-free comparison) reads it here.
    """

    name: str
    label: str
    neighbours: int | None
    target_grid: str
    axes: tuple
    five_d: bool
    marker: str
    rank: int
    weights: WeightsFn
    opt_in: bool = False
    stage: str | None = None
    first_pass: str | None = None

    def __post_init__(self):
        if self.target_grid not in TARGET_GRIDS:
            raise ValueError(f"method {self.name!r}: target_grid = {self.target_grid!r}: must be one of "
                             f"{', '.join(TARGET_GRIDS)}")
        if any(x not in AXES for x in self.axes) or (not self.axes) != (self.target_grid == "none"):
            raise ValueError(f"method {self.name!r}: axes = {self.axes!r}: a tuple from {', '.join(AXES)}, "
                             f"empty exactly when target_grid = 'none'")
        if (self.first_pass is None) != (self.stage is None):
            raise ValueError(f"method {self.name!r}: stage = {self.stage!r}, first_pass = {self.first_pass!r}: a "
                             f"method made by a later stage names the first pass it is made from, and only such a one")
