"""NeuroSLAM (Yu et al. 2019): 3-D grid cells and multilayer head-direction cells (notes ``neuroslam.md``)."""

from core.neuroslam.attractor import Kernel, WrappedAttractor
from core.neuroslam.networks import (
    Codes,
    ConjunctivePoseCells,
    GridCellParams,
    HeadDirectionParams,
    injection_energy,
)

__all__ = [
    "Codes",
    "ConjunctivePoseCells",
    "GridCellParams",
    "HeadDirectionParams",
    "Kernel",
    "WrappedAttractor",
    "injection_energy",
]
