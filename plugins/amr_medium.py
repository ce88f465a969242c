"""Mitsuba plugin entry point for the ``amr`` medium.

With ``plugins/`` on ``sys.path`` (or ``PYTHONPATH``), ``import amr_medium``
registers ``<medium type="amr">`` for the active variant and every variant
selected afterwards, so that ``mi.load_file`` can read XML scenes that use it.
Equivalent to ``import mi_amr``.
"""

import mi_amr  # noqa: F401  (importing registers the plugins)
from mi_amr.plugins.medium import AMRMedium  # noqa: F401

__all__ = ["AMRMedium"]
