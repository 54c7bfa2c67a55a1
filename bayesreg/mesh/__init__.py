"""The tetrahedral mesh of the brain and the FE map it defines on grids; the skull and the
elements' orientation as constraints on the mesh's motion; meshing with fTetWild.
"""
