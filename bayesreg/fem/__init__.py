"""Linear-elastic finite elements: element matrices, the stiffness operator ``K``, the interior
solve ``K_ii u_i = -K_ib u_b`` and its preconditioners, the elastic prior's normaliser.
"""
