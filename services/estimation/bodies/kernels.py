"""The compiled kernels the rigid bodies node runs (numba): the blobs' labelling, the triangulation and the labelled
fits."""

from __future__ import annotations

from services.estimation.bodies import fit_kernel, label_kernel
from services.geometry import triangulation_kernel

__all__ = ["warm"]


def warm() -> None:
    """Each kernel run once on a tiny input: compiled (about 20 s), or loaded from numba's cache."""
    triangulation_kernel.warm()
    fit_kernel.warm()
    label_kernel.warm()
