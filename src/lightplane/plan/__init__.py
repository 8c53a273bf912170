"""Calibration planning: the information of a target placement, the next placement that helps most, and when to
stop."""
