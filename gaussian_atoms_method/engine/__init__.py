"""The fit: the atoms' parameters trained against a tilt series, in plain torch.

Rendering the views, the data term's noise and floors, the point-spread kernel read on held-out
views, the convergence checks and what the run does on them, the residual searches, the final
refit and the results.  No nerfstudio import: the nerfstudio layer adapts this to its trainer
and viewer.
"""
