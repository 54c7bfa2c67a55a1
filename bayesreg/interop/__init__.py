"""Displacement fields as the files ITK, ANTs and 3D Slicer read; the FE map at points and
inverted on a grid; ANTs SyN (through ANTsPy) as a reference registration.
"""
