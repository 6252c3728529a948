"""Simulate a commercial automotive 4D radar from camera + lidar inputs (Song et al., IROS 2025)."""

import os

__version__ = "0.1.0"

# oneDNN (torch's CPU convolutions) 3.x crashes with SIGSEGV in its AVX-512 1x1-convolution
# weight-gradient kernel on some AVX-512 AMD EPYC machines (seen 2026-12-01 in Dis-Net training,
# gdb: jit_avx512_common_1x1_convolution_bwd_weights_t). Its AVX2 kernels train as fast here
# (0.73 vs 0.71 s per Dis-Net step). Read by oneDNN at its first primitive, so it holds wherever
# the package is imported before training starts, dask workers included (they inherit os.environ).
# Set ONEDNN_MAX_CPU_ISA yourself (e.g. to ALL) to override. This is the package's one piece of
# work at import time, on purpose: oneDNN reads the variable once, so setting it later (when
# training starts) would come too late in a process that already ran a convolution.
os.environ.setdefault("ONEDNN_MAX_CPU_ISA", "AVX2")
