"""mapserver: a multisession map server for brain-inspired (RatSLAM-family) SLAM."""

import logging

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())
