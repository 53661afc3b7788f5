"""depthgt: ground-truth depth datasets from raw RGB-D video by local frame sets."""

__version__ = "0.1.0"
