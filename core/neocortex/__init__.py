"""PoseidonSLAM's neocortical front-end: embedding → LSBH SDR → HTM spatial pooler and temporal memory → view cells.

Selected by ``frontend = "sdr-htm"``; :class:`NeocortexViewCells` has the interface of
:class:`core.localview.LocalViewCells`. Imported lazily by the engine, so LVC runs never load torch.
"""

from core.neocortex.backbones import WeightsError
from core.neocortex.viewcells import NeocortexViewCells

__all__ = ["NeocortexViewCells", "WeightsError"]
