"""Live sensor: frame sources (cameras, files, the simulated sensor), laser and turntable control, the live
processing loop and its local web page."""
