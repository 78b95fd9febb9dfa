"""The one error type of the tilt-series readers and format: the input cannot be used as given."""


class TiltSeriesError(ValueError):
    """A tilt series cannot be used as given; the message names the file or option."""
