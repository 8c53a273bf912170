"""The laser stripe: sub-pixel centre lines (Steger), the numba kernels, laser selection by colour and region."""
