"""Session set-up shared by every test module."""

from clrecon.core import drivers

# The wheel-installed OpenCL drivers (Intel's CPU runtime) are registered with the ICD loader
# before any test module queries the platforms: the loader reads OCL_ICD_VENDORS only once.
drivers.register_wheel_drivers()
