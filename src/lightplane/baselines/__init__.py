"""Baseline methods lightplane is compared with (Zhou's planar-target method)."""
