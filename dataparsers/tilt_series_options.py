"""The options that name a tilt series and override its manifest: ``tilt-series --data DIR ...``
on the command line, for ``gaussian-atoms train`` and nerfstudio's dataparser alike
(:class:`dataparsers.tilt_series_dataparser.TiltSeriesDataParserConfig` is nerfstudio's
dataparser config with these)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional, Tuple

from .tilt_series_format import TiltSeries, load_tilt_series


@dataclass
class TiltSeriesOptions:
    """A tilt series directory (``tilt_series.json``) or explicit files."""

    data: Path = Path("data/tilt_series")
    """Directory holding tilt_series.json (or the manifest file itself)."""
    projections: Optional[Path] = None
    """Projection stack (.npy/.npz, .tif, .mrc/.st/.ali, .emd/.h5, .mat), relative to data;
    overrides the manifest."""
    angles_deg: Optional[Path] = None
    """Tilt angles in degrees (text, IMOD .tlt/.rawtlt, .npy, .mat; N values or N x 3 Euler),
    relative to data; overrides the manifest."""
    pixel_size_A: Optional[float] = None
    """Pixel size in Å; overrides the manifest."""
    tilt_axis: Optional[Literal["x", "y"]] = None
    """World axis of the tilt (README: convention); overrides the manifest."""
    truth: Optional[Path] = None
    """True atoms (any ASE-readable file) for scoring; overrides the manifest."""
    dataset: Optional[str] = None
    """Variable (.mat, .npz) or dataset / EMD group (.h5, .emd) holding the projections, when the
    file holds several."""
    tilt_index_axis: Optional[int] = None
    """Array axis of the tilt index (default: the format's convention; last for MATLAB)."""
    angles_variable: Optional[str] = None
    """Variable of a .mat angle file that holds the angles, when it holds several."""
    centre_px: Optional[Tuple[float, float]] = None
    """Detector (row, col) of the tilt axis; default the middle. RESIRE/GENFIRE data: (n//2, n//2)."""
    tilt_axis_angle_deg: Optional[float] = None
    """Angle of the tilt axis in the images (degrees, counterclockwise with the rows pointing up,
    from the direction tilt-axis names); default the manifest's, an IMOD MRC header's, or 0."""

    species: Optional[str] = None
    """The specimen's elements, e.g. Ta or Fe,Pt: they set the shortest distance two atoms may
    keep (the hard core); without them it is read from the atoms found.  Overrides the manifest."""
    euler_convention: Optional[Literal["zyz", "zyx"]] = None
    """Axes of N x 3 Euler angles (phi, theta, psi): zyz as GENFIRE writes them (default), zyx
    as RESIRE does.  Overrides the manifest."""

    drop_views: Optional[str] = None
    """Views to leave out: their indices in the file (3,7) or their tilts (-40deg), e.g. a view
    that holds NaN or a blank frame.  Overrides the manifest."""
    contrast: Optional[Literal["adf", "phase"]] = None
    """What the views show: adf (ADF-STEM, the default) or phase (ptychographic phase images);
    the run's own replica draws its atoms so.  Overrides the manifest."""

    def load(self, data: Optional[Path] = None) -> TiltSeries:
        """The tilt series these options name (``data`` overrides the directory); raises
        :class:`~dataparsers.errors.TiltSeriesError` naming the file and the problem."""
        return load_tilt_series(
            self.data if data is None else data,
            self.projections,
            self.angles_deg,
            self.pixel_size_A,
            self.tilt_axis,
            self.truth,
            self.dataset,
            self.tilt_index_axis,
            self.angles_variable,
            self.centre_px,
            self.tilt_axis_angle_deg,
            self.species,
            self.euler_convention,
            self.drop_views,
            self.contrast,
        )
