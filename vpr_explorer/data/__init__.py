"""Datasets in: traversal folders, the field's benchmark layouts, ground truth, the demo route and worked examples."""
