"""Reports: the HTML report and its plots, and the demo that runs the whole chain."""
