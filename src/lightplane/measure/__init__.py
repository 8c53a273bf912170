"""Measurement: profiles and triangulation of stripe frames, scans placed by their motion, point clouds, sensor files and batches."""
