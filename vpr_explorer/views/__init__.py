"""The numbers behind the explorer's views, and the Plotly figures, maps and text tables drawn from them."""
