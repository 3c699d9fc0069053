"""``python -m wrinkles ...`` runs the ``wrinkles`` command line (see :mod:`wrinkles.cli`)."""

from wrinkles.cli import entry

entry()
