"""Evaluation: cross-ratio distances on chessboards, shape fits, and the paper's simulation study."""
