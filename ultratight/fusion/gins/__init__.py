"""INS/GNSS integration of recorded sensor logs (``ultratight integrate``): alignment, the
loose/tight error-state filter with the seed filters as cores, zero-velocity and non-holonomic
updates, χ² gating, the RTS smoother, and the outage evaluation against a reference."""
