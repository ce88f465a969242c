"""The host-structure cache: built host structures (blocks made from
per-cell records, bricks, brick trees and their value ranges, the kd-tree's
input grid, value masks) keyed by the identity of their data object and a
key of the build options, so that media on one data object build each once
(`mi_amr.core.identity_cache`: entries go with the data object, nothing is
stored on it)."""

from __future__ import annotations

from ..core.identity_cache import IdentityCache

#: Built host structures per data object and options key.
StructureCache = IdentityCache

#: The process-wide cache the pipeline uses.
HOST_CACHE = StructureCache()
