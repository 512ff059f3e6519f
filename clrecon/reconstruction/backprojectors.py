"""Names of the reconstruction's backprojectors (``recon.backprojector``); imports nothing.

``direct``
    Fan-beam FBP straight from the fan views: cosine weight, ramp filter of each rebinned row
    (once, before the interpolation), distance-weighted fan backprojection of V views over
    2 pi (:mod:`clrecon.reconstruction.fbp`). The paper runs use it.
``parallel-rebin``
    Each interpolated fan sinogram rebinned to V/2 parallel views over pi (direct and
    conjugate rays merged), ramp-filtered in s, parallel backprojection
    (:mod:`clrecon.reconstruction.parallel_fbp`).

The config layer (:mod:`clrecon.config.scene`) validates ``recon.backprojector`` against
:data:`BACKPROJECTORS`; :mod:`clrecon.reconstruction.reconstruct` dispatches on it.
"""

BACKPROJECTORS = ("direct", "parallel-rebin")
