"""Ground truth: scene index, frame sets, frame cache, GT renderer, patches, dataset assembly, global-reconstruction GT."""
