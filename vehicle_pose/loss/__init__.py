"""The losses the search minimises: the illumination-invariant loss, its alternatives and the edge term."""
