"""Session set-up shared by every test module."""

import os

import pytest

from clrecon.core import drivers

# The wheel-installed OpenCL drivers (Intel's CPU runtime) are registered with the ICD loader
# before any test module queries the platforms: the loader reads OCL_ICD_VENDORS only once.
drivers.register_wheel_drivers()


@pytest.fixture(autouse=True)
def _no_driver_preference_left_behind():
    """A run's timed driver choice is process-wide (clrecon/pipeline/driver_choice.py): drop it after each
    test, so that no test inherits the driver another test's run preferred."""
    yield
    os.environ.pop(drivers.PREFERENCE_ENV, None)
