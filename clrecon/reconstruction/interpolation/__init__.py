"""Phase-space interpolation: one module per method, registered in :data:`METHODS`.

``weights`` is the dispatcher (:func:`batch_weights`, :func:`method_weights`), ``apply`` the
OpenCL weighted sums of rows; ``base`` defines :class:`Method`, ``registry`` the registry and
the lists derived from it. A new method is one module here that registers itself, imported
below (``docs/extending.md``). The import order below is the registration order, i.e. the
``recon.methods`` default order.

These modules import only ``clrecon.core`` (the config layer imports the registry).
"""

# isort: off
# The methods, in registration order (keep it: it is the recon.methods default order).
from clrecon.reconstruction.interpolation import barycentric
from clrecon.reconstruction.interpolation import local_linear
from clrecon.reconstruction.interpolation import r4dct
from clrecon.reconstruction.interpolation import nearest
from clrecon.reconstruction.interpolation import bin
from clrecon.reconstruction.interpolation import helical
from clrecon.reconstruction.interpolation import cv_tuned
from clrecon.reconstruction.interpolation import mc
from clrecon.reconstruction.interpolation import mcir
# isort: on

from clrecon.reconstruction.interpolation.apply import (
    DeviceRows,
    apply_weights_interleaved,
    apply_weights_reference,
)
from clrecon.reconstruction.interpolation.base import Method, Options
from clrecon.reconstruction.interpolation.registry import (
    METHODS,
    by_rank,
    default_methods,
    figure_order,
    first_pass,
    five_d_methods,
    markers,
    method_names,
    register_method,
    resp_grid_methods,
    second_pass_methods,
)
from clrecon.reconstruction.interpolation.weights import NoCandidatesError, Weights, batch_weights, method_weights

__all__ = [
    "METHODS", "DeviceRows", "Method", "NoCandidatesError", "Options", "Weights",
    "apply_weights_interleaved", "apply_weights_reference", "barycentric", "batch_weights", "bin", "by_rank",
    "cv_tuned", "default_methods", "first_pass",
    "figure_order", "five_d_methods", "helical", "local_linear", "markers", "mc", "mcir", "method_names",
    "method_weights",
    "nearest", "r4dct", "register_method", "resp_grid_methods", "second_pass_methods",
]
