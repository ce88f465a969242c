"""Mitsuba plugins: the ``amr`` medium and the ``amrvolpath`` integrator."""
