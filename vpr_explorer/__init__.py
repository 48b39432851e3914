"""VPR Threshold Explorer: per-place thresholds from negative Gaussian mixture statistics.

Implements N. Trinh, D. Lyons, "Adaptive Thresholding for Visual Place Recognition using
Negative Gaussian Mixture Statistics" (IEEE RCC 2025, arXiv 2512.09071). The folders follow
the data flow (``docs/architecture.md``); each package's docstring maps its modules:

* ``data``: datasets in every layout, their ground truth, the demo route and examples.
* ``descriptors``: global image descriptors by name, through an on-disk cache; files from
  elsewhere; float16 memory maps; extraction on Ray.
* ``method``: places, negative statistics, thresholds, retrieval and decisions.
* ``protocols``: the evaluation protocols, the blocked fast path, shared scores,
  precision–recall, sweeps, runs compared.
* ``views``: the numbers behind the explorer's views, and the figures, maps and tables.
* ``pipeline``: the stages wired together, what the command line, the app and the recorder call.
* ``recording``: traversal playback into a rerun recording.
* ``app``: the Streamlit explorer (the only package that imports streamlit).
* ``cli``: the ``vpr-explorer`` command line, one module per command.
* ``settings`` and ``errors``: where things live on disk, default thread counts, and the
  one error type for bad input.
"""

from vpr_explorer.errors import VPRInputError

__all__ = ["VPRInputError"]
__version__ = "0.1.0"
