"""Test-session setup: single-threaded BLAS, as the daemon runs (service/cli.py).

The estimators multiply small matrices (3x3 to ~30x4500); a threaded OpenBLAS on a busy 2-core
machine spends its time in locking and spinning: one normal-equation build of method A took 51 ms per
call threaded (a 4500x27 Gram matrix: 144 ms threaded, 0.27 ms single-threaded on the loaded
development machine), and the 240 s method-D flight (tests/test_pipeline_deviation.py) took 106 s
against 22 s. pytest imports this file before any test module imports numpy.
"""
import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
