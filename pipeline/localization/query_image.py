"""A query's image and its global descriptor, as every way of localizing it reads them (a query alone,
``pipeline.localization.shard``; the images of a rig frame, ``pipeline.localization.rigs``)."""

import dataclasses
import logging
from typing import Optional, Tuple

import numpy as np

from pipeline.images import ImageReadError, read_image_for
from pipeline.localization.candidates import QueryCache
from pipeline.mapping.features import global_descriptor
from pipeline.queries import QueryRecord

logger = logging.getLogger(__name__)


def fit_query(query: QueryRecord) -> Tuple[QueryRecord, np.ndarray]:
    """The query's image (``pipeline.images.read_image_for``: decoded in full, its size checked
    against the camera) and the query with the camera that fits it; a resized copy is noted in
    the record. Raises ImageReadError naming the file."""
    rgb, camera, note = read_image_for(query.path, query.camera)
    if note:
        logger.warning("%s: %s", query.name, note)
        query = dataclasses.replace(query, camera=camera, notes=query.notes + (note,))
    return query, rgb


def describer(reader, localizer, rgb: Optional[np.ndarray], cache: QueryCache):
    """The query's global descriptor, computed when first asked (the network at the coarsest
    image scale, kept in ``cache`` for the refinement)."""
    def describe() -> np.ndarray:
        k_last = len(reader.conf.image_scales) - 1
        pred = cache.network(k_last, lambda: localizer.predict(rgb, k_last))[0]
        return global_descriptor(pred["features"][-1][0], reader.conf.descriptor).cpu().numpy()
    return describe


def read_query(query: QueryRecord) -> Tuple[QueryRecord, Optional[np.ndarray], str]:
    """A query ready to run: (the query with the camera that fits its file, its image, "") after its list line,
    camera and image are checked (``fit_query``), or (the query, None, the reason it cannot run)."""
    if query.error:
        return query, None, query.error
    reason = query.camera.check()
    if reason:
        return query, None, reason
    try:
        query, rgb = fit_query(query)
    except ImageReadError as e:
        return query, None, str(e)
    return query, rgb, ""
