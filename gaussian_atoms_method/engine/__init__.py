"""The fit: the atoms' parameters trained against a tilt series, in plain torch.

:class:`~.fit.AtomFit` owns the parameters and the view set; :mod:`.training` runs it and
:mod:`.run` takes a tilt series to a run directory (``gaussian-atoms train`` and
``ga.reconstruct``).  Around them: rendering the views, the data term's noise and floors, the
point-spread kernel read on held-out views, the convergence checks and what the run does on
them, the residual searches, the final refit and the results.  No nerfstudio import: the
nerfstudio layer is this fit seen through splatfacto's interface.
"""
