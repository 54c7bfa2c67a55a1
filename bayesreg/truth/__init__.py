"""Synthetic truths: the smooth brain shift and its FE solve, truths the model did not make,
and the paper's constrained truth under the skull.
"""
