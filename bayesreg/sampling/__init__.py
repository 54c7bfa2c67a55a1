"""Sampling: the kernels (BlackJAX-style ``init`` / ``step``), the chain scheduler, the
driver (warm-up, chunks, stop rule), convergence and diagnostics.
"""
