"""Embedding of the shell in the coarse body: surface, subdivision, B matrix, clusters and H.

Modules (Remillard & Kry 2013, Algorithm 1 of the draft):
  * ``surface``: outward boundary surface of a tet mesh (pure numpy);
  * ``subdivision``: linear / Loop subdivision as sparse matrices ``S_l`` (numpy/scipy);
  * ``embedding``: the matrix B for a dolfinx P1/P2 space, and the rank-independent gathering
    of a distributed mesh's surface (the only module that imports dolfinx);
  * ``clusters``: cluster centres, the constraint matrix H and the partition (numpy/scipy).
"""
