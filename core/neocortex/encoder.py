"""Per-modality embedding y = f(o) (PoseidonSLAM Eq. 4.1), CPU by default, CUDA when present.

Two kinds:

* ``frontend_backbone = "none"`` (the weight-free encoder): the image's local-view template (crop,
  greyscale, block average to ``template_y_size × template_x_size``, the LVC normalisations; exactly
  :meth:`core.localview.LocalViewCells.make_template`), flattened and centred on its mean. No learnt
  weights: the fixed LSBH projection then does all the hashing.
* ``shufflenetv2`` / ``alexnet``: the flattened mid-level features of a pretrained backbone loaded from
  ``frontend_weights`` (see :mod:`core.neocortex.backbones`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from core.arrays import UInt8Array
from core.config import ConfigError
from core.localview import LocalViewCells
from core.neocortex.backbones import AlexNet, ShuffleNetV2, build_backbone, preprocess

if TYPE_CHECKING:
    from core.config import Params

CNN_INPUT = 224


def resolve_device(name: str) -> torch.device:
    """Return the torch device for ``frontend_device`` (auto: CUDA when available, else CPU).

    Raises:
        ConfigError: ``cuda`` asked for where torch sees no CUDA device.
    """
    if name == "cuda" and not torch.cuda.is_available():
        msg = "frontend_device = 'cuda' but torch sees no CUDA device (use auto or cpu)"
        raise ConfigError(msg)
    if name == "cuda" or (name == "auto" and torch.cuda.is_available()):
        return torch.device("cuda")
    return torch.device("cpu")


class Encoder:
    """Maps a camera image to its embedding (1, dims) float32 on the front-end's device."""

    def __init__(self, params: Params, device: torch.device) -> None:
        self.params = params
        self.device = device
        self.backbone: ShuffleNetV2 | AlexNet | None = None
        if params.frontend_backbone == "none":
            self._templates = LocalViewCells(params)
            self.dims = params.template_y_size * params.template_x_size
        else:
            self.backbone = build_backbone(params.frontend_backbone, params.frontend_weights, device)
            with torch.no_grad():
                probe = torch.zeros((1, 3, CNN_INPUT, CNN_INPUT), device=device)
                self.dims = int(self.backbone.embed(probe).shape[1])

    def __call__(self, image: UInt8Array) -> torch.Tensor:
        """Return the embedding y of ``image`` (uint8 (H, W) or (H, W, 3))."""
        if self.backbone is None:
            template, _ = self._templates.make_template(image)
            y = torch.from_numpy(template.reshape(1, -1).astype(np.float32))
            return (y - y.mean()).to(self.device)
        with torch.no_grad():
            return self.backbone.embed(preprocess(image, self.device, CNN_INPUT))
