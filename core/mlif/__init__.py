"""PC-MLIF: RatSLAM pose cells as memristive spiking networks (Pirozzo et al., OCEANS 2024; ``pc_model = mlif``)."""

from core.mlif.network import MlifNetwork
from core.mlif.neuron import MemristorParams, MlifState, NeuronParams
from core.mlif.posecells import MlifPoseCells

__all__ = ["MemristorParams", "MlifNetwork", "MlifPoseCells", "MlifState", "NeuronParams"]
