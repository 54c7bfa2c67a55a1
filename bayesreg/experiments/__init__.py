"""Experiments built on the main job: simulation-based calibration and sweeps of many runs
on Dask.
"""
