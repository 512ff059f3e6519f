"""Packed layout of one quadric object: one row of ``STRIDE`` float64 (``docs/simulation.md`` "Analytic projector").

Shared by the phantoms that build objects (:mod:`clrecon.simulation.phantoms.analytic`), the
projector (:mod:`clrecon.simulation.projector`) and the voxeliser
(:mod:`clrecon.simulation.voxelise`); ``kernels/record.h`` mirrors the records built from it.
"""

KIND = 0                #: 0 = absent, 1 = ellipsoid, 2 = elliptic cylinder
MU = 1                  #: additive density (1/mm)
CENTRE = slice(2, 5)
AXES = slice(5, 14)     #: rotation R row-major (R[i, k] at 5 + 3 i + k): column k = local axis k
SEMI = slice(14, 17)    #: semi-axes (cylinder: two transverse semi-axes, half length)
PLANES = slice(17, 25)  #: two clip half-spaces (nx, ny, nz, d): n . x <= d; n = 0, d = 1: none
CUT0, CUT_LEN = 25, 16  #: cut k at CUT0 + k CUT_LEN: mode, centre (3), axes (9, as AXES), semi (3)
N_PLANES, N_CUTS = 2, 2
STRIDE = CUT0 + N_CUTS * CUT_LEN  # 57
KIND_NONE, KIND_ELLIPSOID, KIND_CYLINDER = 0, 1, 2
CUT_NONE, CUT_SUBTRACT, CUT_INTERSECT = 0, 1, 2


def cut_fields(k: int):
    """(mode index, centre slice, axes slice, semi slice) of cut ``k`` in a packed row."""
    b = CUT0 + k * CUT_LEN
    return b, slice(b + 1, b + 4), slice(b + 4, b + 13), slice(b + 13, b + 16)

