"""Device code of rwwarp: Warp kernels (``trace``, ``splat``) and OpenCL C sources (``opencl/``).

This package is installed as ``rwwarp.kernels``. Modules here import nothing but warp.
"""
