"""The gtkit annotator: a PySide6 desktop application over the project's files.

It reads and writes only what the command line reads and writes: ``tiepoints.json`` (every
edit saved atomically at once), ``review.json`` (accept / reject / needs-work per image) and
its own UI state in ``work/annotate/session.json``. Open it with ``gtkit annotate DIR``.
Qt lives only in this package; :mod:`gtkit` never imports it.
"""
