"""Building the structures a medium asks for: the registries of traversals
and samplings (`strategies`), how each component is built, uploaded and
sized (`components`), and `pipeline.Structures`, the glue a medium owns
(docs/design.md section 6). Above the host structures (`mi_amr.structures`)
and their device halves (`mi_amr.device`), below the plugins."""

from .pipeline import StructureOptions, Structures
from .strategies import SAMPLINGS, TRAVERSALS

__all__ = ["SAMPLINGS", "StructureOptions", "Structures", "TRAVERSALS"]
