"""Synthetic world with exact ground truth: sensor geometry, point-level
simulation (paper §3) and image rendering (circle targets, scans, and calibration
targets: chessboards, circle grids, asymmetric circle grids and ChArUco boards,
:func:`lightplane.simulate.render.render_target_dataset`).  Import the submodules
(``lightplane.simulate.scene``, ``lightplane.simulate.render``, ...)."""
