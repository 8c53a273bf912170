"""Motion between frames: the motion model, turntable calibration and its refinement from scans."""
