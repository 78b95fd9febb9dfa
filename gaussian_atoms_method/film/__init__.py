"""A film wider than the field of view, fitted in overlapping sub-areas on Ray and joined into
one set of atoms with the evidence of the overlap (:mod:`.film`)."""
