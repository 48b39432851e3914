"""Streamlit helpers of the explorer app: the view state, the caches, error and progress display.

Only ``app.py`` and ``pages/`` import this package; the library (``vpr_explorer``) never does.
"""
