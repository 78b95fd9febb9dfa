"""Density control: how many Gaussians there are and where (duplicate, prune, merge), as a
strategy object that holds its own state and acts on the parameter dict and the optimisers'
state (:mod:`.strategy`), the mean of the optimiser's iterates over each refine interval
(:mod:`.averaging`), and the re-indexing of parameters and Adam moments that every such
change needs (:mod:`.remap`).  Torch and numpy only; no nerfstudio."""
