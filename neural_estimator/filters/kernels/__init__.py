"""The classical filters' compiled (numba) kernels."""
