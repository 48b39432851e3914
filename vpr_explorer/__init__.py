"""VPR Threshold Explorer: per-place thresholds from negative Gaussian mixture statistics.

Implements N. Trinh, D. Lyons, "Adaptive Thresholding for Visual Place Recognition using
Negative Gaussian Mixture Statistics" (IEEE RCC 2025, arXiv 2512.09071). The modules follow
the data flow: ``datasets`` -> ``places`` -> ``descriptors`` -> ``stats`` -> ``thresholds``
-> ``retrieval`` -> ``evaluation``; ``plots`` and ``recording`` are leaves.
"""

from vpr_explorer.errors import VPRInputError

__all__ = ["VPRInputError"]
__version__ = "0.1.0"
