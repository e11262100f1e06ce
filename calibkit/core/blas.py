"""One BLAS thread for a block of small matrix work.

OpenBLAS's threads make small matrix products and factorisations 3-100x slower in CPU
time on a busy 2-core machine (they spin waiting for each other): a 300 x 123 SVD took
2.6 s against 0.016 s, and labelling a take from the marker set alone (thousands of
products with a 1681 x 1681 table) 4.3 s against 1.5 s. These sizes are fastest on one
thread, so every BLAS loaded is limited to one thread for the block (threadpoolctl).
"""

from __future__ import annotations


def one_blas_thread():
    """A context manager limiting every loaded BLAS to one thread inside it."""
    # deferred on purpose: loads threadpoolctl only where used
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api="blas")
