"""The built GT dataset in users' hands.

* :class:`GTDataset`: a ``torch.utils.data.Dataset`` over the split manifests, read
  straight from the frame-set shards (:mod:`depthgt.data.dataset`).
* :func:`export_dataset`: the dataset as plain files other tools read, 16-bit PNG in
  millimetres or float EXR, with one index (:mod:`depthgt.data.export`).

Layer: above :mod:`depthgt.gt` (reads its store), below :mod:`depthgt.enhance` (the
trainer reads its patches through :class:`GTDataset`).
"""

from depthgt.data.dataset import KINDS, GTDataset, training_fields
from depthgt.data.export import FORMATS, export_dataset

__all__ = ["GTDataset", "KINDS", "training_fields", "export_dataset", "FORMATS"]
