"""Streamlit helpers of the explorer app: the view state, the caches, error and progress display.

Only the app's entry script and pages import this package; the library never does.
"""
