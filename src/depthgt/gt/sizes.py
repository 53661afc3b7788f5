"""The measured size of a frame set in the shard format (:mod:`depthgt.gt.store`), what
the run's space check (:mod:`depthgt.gt.space`) plans with.

A module of constants only (no import): the workflow's ``onstart`` reads them through
:mod:`depthgt.gt.space` before the first job, without the shard writer's imports
(NumPy, OpenCV, OpenEXR).
"""

from __future__ import annotations

__all__ = ["MEASURED_FRAMESET_BYTES", "MEASURED_RESIZE", "MEASURED_FRAMESET_FIXED_BYTES"]

#: bytes on disk of one frame set in this format at the working resolution
#: :data:`MEASURED_RESIZE` (its share of a shard), measured (bench/README.md "Bytes per
#: frame set", format 3): 0.235 MB over the 33 frame sets of the two real recordings
#: (7-Scenes 0.241, TUM 0.234), 0.271 MB on synthetic rooms with their clean truth; the
#: run's space check (:mod:`depthgt.gt.space`) plans with them and the README's figures
#: (0.59 TB for every frame of ScanNet) follow from them (tests/test_docs_facts.py)
MEASURED_FRAMESET_BYTES = {"real": 235_000, "synthetic": 271_000}
#: the working resolution (``resize``) of :data:`MEASURED_FRAMESET_BYTES`
MEASURED_RESIZE = 256
#: the part of :data:`MEASURED_FRAMESET_BYTES` that does not grow with the resolution:
#: the JSON members (~5 kB), the patch record (~2 kB), and the images' headers and the
#: zip's records (~7 kB); fitted to shards measured at ``resize: 64`` (28.0 kB per real,
#: 29.5 kB per synthetic frame set) with the sizes at 256 above
MEASURED_FRAMESET_FIXED_BYTES = 14_000
