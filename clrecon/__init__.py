"""clrecon: simulate helical CT of a breathing, beating thorax and reconstruct 5DCT.

Pipeline (one module per stage): scene -> signals -> geometry (per-projection table)
-> phantom/projector -> noise -> store -> rebin (SSRB) -> interpolate (phase space)
-> fbp -> groundtruth/metrics -> report.
"""

__version__ = "0.1.0"

#: Bumped whenever the projector or phantom changes what a stored projection holds.
PROJECTOR_VERSION = 2  # 2: the committed phantom + culled projector (1 was the pre-release skeleton)
