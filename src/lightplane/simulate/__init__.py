"""Synthetic world with exact ground truth: sensor geometry, point-level
simulation (paper §3) and image rendering.  Import the submodules
(``lightplane.simulate.geometry``, ``lightplane.simulate.render``, ...)."""
