"""The outputs of a finished run: nodal and voxel statistics of the posterior field, figures,
the ArviZ tree, error tables and the verdict.
"""
