"""The numbers behind the explorer's views, and the figures, maps and text tables drawn from them.

* ``numbers``: the numbers behind each view of a dataset value (places from the layout,
  frames or metres; one place, one query, the overview; sampling and budgets for big
  datasets; decisions over a memory-mapped database).
* ``plots``: every Plotly figure, from those numbers.
* ``maps``: the map of a position-tagged dataset (places, queries, one query's radius).
* ``compare_plots``: figures of runs compared (precision–recall and trade-off curves per run).
* ``report``: evaluations as text tables (the paper's Table 1 layout) and CSV rows.
* ``bench_plots``: the acceptance bench's table rows and figures (every rule's curve,
  VPR_Tutorial's curves, discovered places).
* ``reasons``: each acceptance rule's reasons for one query, in words and figures.
* ``failures``: which queries a method fails and how, drawn as prediction grids (PNG) with
  an index page.
"""
