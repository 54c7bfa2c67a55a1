"""Images with their affine, tissue labels, the data sources and an optical-flow registration:
what the method starts from (world mm; images carry their voxel-to-world affine).
"""
