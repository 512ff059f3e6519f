"""Names of the reconstruction's backprojectors (``recon.backprojector``); imports nothing.

``direct``
    Fan-beam FBP straight from the fan views: cosine weight, ramp filter of each rebinned row
    (once, before the interpolation), distance-weighted fan backprojection of V views over
    2 pi (:mod:`clrecon.reconstruction.fbp`). The paper runs use it.
``parallel-rebin``
    Each interpolated fan sinogram rebinned to V/2 parallel views over pi (direct and
    conjugate rays merged), ramp-filtered in s, parallel backprojection
    (:mod:`clrecon.reconstruction.parallel_fbp`).

No faster option meets the accuracy goal of issue 20 (every MAE within 0.5 HU of ``direct``'s):
any resampling of the filtered sinogram before the backprojection (rebinning, tile decimation as
in a hierarchical backprojection, gridding) smooths the band above the image grid's Nyquist
that the direct path's interpolation folds into the pixels, and moves the noisy MAEs by 3 HU
or more at any cost below the direct one (docs/results/backprojectors.md, "A backprojection faster than
`direct`"; the float64 study in ``benchmarks/studies/hierarchical/``).

The config layer (:mod:`clrecon.config.scene`) validates ``recon.backprojector`` against
:data:`BACKPROJECTORS`; :mod:`clrecon.reconstruction.reconstruct` dispatches on it.
"""

BACKPROJECTORS = ("direct", "parallel-rebin")
