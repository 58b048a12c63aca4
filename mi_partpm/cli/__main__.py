"""``python -m mi_partpm.cli``: the ``partpm`` command (as MPI jobs start it)."""
import sys

from . import main

sys.exit(main())
