"""Errors the fit raises for what the user gave."""


class OptionError(ValueError):
    """A model option (or a combination of them) that cannot be honoured; the message names it."""
