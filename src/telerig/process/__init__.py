"""The annotation pipeline (``telerig process``): recorded and external video into annotated clips.

Stages, each pure, idempotent and resumable with recorded provenance: frame filtering (motion
heuristics and hand detection), temporal action segmentation, clip extraction, vision-language
annotation and the dataset layout. It sits beside :mod:`telerig.export` in the layer contract; the
two never import each other (annotations reach exports through :mod:`telerig.store.segments_file`).
"""
