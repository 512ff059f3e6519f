"""Version numbers: the package's, and the projector's (what a stored projection holds)."""

__version__ = "0.1.0"

#: Bumped whenever the projector or phantom changes what a stored projection holds.
PROJECTOR_VERSION = 3  # 3: + the LV-wall target lesion; 2: the committed phantom + culled projector
#                        (1 was the pre-release skeleton)
