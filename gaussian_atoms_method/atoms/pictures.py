"""The run's pictures, drawn with matplotlib from plain arrays: ``slices.png`` (central slices
of the potential with the atoms overlaid) and ``classes.png`` (the Gaussians' population by
class).  numpy and matplotlib only, so a child process draws them without importing torch
(:mod:`.picture_process`).  Each file is written atomically: complete or absent."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gaussian_atoms_method.atoms.atom_set import _atomic_write


def pyplot():
    """matplotlib's pyplot on the Agg backend (files only, no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def draw_slices(slices, output: Path, title: str = "") -> Path:
    """``slices`` (:class:`~gaussian_atoms_method.atoms.slices.SlicePlanes`) as three panels,
    the predicted atoms as open circles and the true atoms as crosses, into ``output``."""
    plt = pyplot()
    names = "xyz"
    fig, axes = plt.subplots(1, 3, figsize=(15, 5.2))
    for i, (ax, (n, u, v)) in enumerate(zip(axes, slices.axes)):
        ax.imshow(slices.planes[i], cmap="gray", extent=slices.extents[i])
        for points, style in (
            (slices.true_points[i], dict(marker="x", color="tab:red", s=22, linewidths=1.0, label="true")),
            (
                slices.predicted_points[i],
                dict(marker="o", facecolors="none", edgecolors="tab:cyan", s=40, linewidths=1.0, label="predicted"),
            ),
        ):
            if points is not None:
                ax.scatter(points[:, 0], points[:, 1], **style)
        ax.set_xlabel(f"{names[v]} (Å)")
        ax.set_ylabel(f"{names[u]} (Å)")
        ax.set_title(
            f"{names[u]}{names[v]} slice at {names[n]} = {slices.centre_A[n]:.1f} Å (atoms within {slices.slab_A:g} Å)"
        )
    axes[0].legend(loc="upper right", fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    output = Path(output)
    _atomic_write(output, lambda p: fig.savefig(p, dpi=90, format="png"))
    plt.close(fig)
    return output


def write_population_png(
    masses: np.ndarray,
    sigmas_A: np.ndarray,
    atoms: np.ndarray,
    classes: np.ndarray,
    n_classes: int,
    beyond_field: tuple[np.ndarray, np.ndarray] | None,
    path,
) -> Path:
    """The population of the Gaussians: width against mass (log axes), each atom (``atoms``,
    (N,) bool) coloured by its class (``classes``, 1..``n_classes``), the non-atoms in the field
    (outside the support, in a class apart from the atoms, inside a reported atom's hard core) as crosses and those
    beyond the field of view (``beyond_field``: their masses and
    widths) as grey dots (:func:`~gaussian_atoms_method.atoms.classification.classify_gaussians`
    gives the classes)."""
    plt = pyplot()
    import matplotlib.ticker

    fig, ax = plt.subplots(figsize=(5.5, 4.2), dpi=120)
    if beyond_field is not None and len(beyond_field[0]):
        ax.scatter(
            beyond_field[0], beyond_field[1], s=4, c="0.75", label=f"beyond the field of view ({len(beyond_field[0])})"
        )
    for k in range(1, n_classes + 1):
        pick = atoms & (classes == k)
        ax.scatter(masses[pick], sigmas_A[pick], s=5, label=f"class {k} ({int(pick.sum())})")
    if np.any(~atoms):
        ax.scatter(
            masses[~atoms], sigmas_A[~atoms], s=18, marker="x", c="k", label=f"non-atoms ({int((~atoms).sum())})"
        )
    ax.set(
        xscale="log",
        yscale="log",
        xlabel="mass (input units x Å²)",
        ylabel="width σ (Å)",
        title="Fitted Gaussians: atoms by class, and non-atoms",
    )
    # a decade or less: label 1, 2 and 5 times powers of ten, not every minor tick (they overlapped)
    for axis in (
        ax.xaxis,
        ax.yaxis,
    ):
        axis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
        axis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda value, _: f"{value:g}"))
        axis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.legend(fontsize=7, markerscale=2)
    fig.tight_layout()
    _atomic_write(path, lambda tmp: fig.savefig(tmp, format="png"))
    plt.close(fig)
    return Path(path)


def write_rdf_png(
    r_A: np.ndarray, g: np.ndarray, hard_core_A: float | None, share_under: float | None, path, title: str = ""
) -> Path:
    """The reported atoms' radial distribution ``g(r)``
    (:func:`~gaussian_atoms_method.atoms.structure_evidence.pair_distribution_function`)
    with the material's hard core shaded: no physical pair lies there."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 3.6), dpi=120)
    ax.plot(r_A, g, color="tab:blue", lw=1.2)
    if hard_core_A is not None:
        label = f"hard core {hard_core_A:.2f} Å" + (
            f" ({share_under:.1%} of atoms inside)" if share_under is not None else ""
        )
        ax.axvspan(0.0, hard_core_A, color="tab:red", alpha=0.15, label=label)
        ax.legend(fontsize=7)
    ax.set(
        xlabel="r (Å)",
        ylabel="g(r)",
        xlim=(0.0, float(r_A[-1]) if len(r_A) else 1.0),
        title=title or "Pair distribution of the reported atoms",
    )
    fig.tight_layout()
    _atomic_write(path, lambda tmp: fig.savefig(tmp, format="png"))
    plt.close(fig)
    return Path(path)
