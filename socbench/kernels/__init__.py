"""Compiled kernels (numba): placeholder docstring, rewritten below."""
