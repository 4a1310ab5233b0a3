"""Geometry below the method: exact distance kernels (numba), pose metrics, the raycaster."""
