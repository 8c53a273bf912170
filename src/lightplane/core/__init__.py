"""Errors, low-level geometry, file input/output and thread settings: the layer everything else stands on."""
