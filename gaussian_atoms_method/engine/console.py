"""The console the fit prints its lines on: rich's, 120 columns wide (as nerfstudio's), so the
lines read the same under either launcher."""

from rich.console import Console

CONSOLE = Console(width=120)
