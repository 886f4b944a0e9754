"""NeuroSLAM (Yu et al. 2019): 3-D grid cells and multilayer head-direction cells (notes ``neuroslam.md``)."""

from core.neuroslam.attractor import Kernel, WrappedAttractor
from core.neuroslam.networks import (
    Codes,
    ConjunctivePoseCells,
    GridCellParams,
    HeadDirectionParams,
    injection_energy,
)
from core.neuroslam.viewlinks import ViewDecay, ViewLinks

__all__ = [
    "Codes",
    "ConjunctivePoseCells",
    "GridCellParams",
    "HeadDirectionParams",
    "Kernel",
    "ViewDecay",
    "ViewLinks",
    "WrappedAttractor",
    "injection_energy",
]
