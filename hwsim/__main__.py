"""``python -m hwsim``: :func:`hwsim.cli.main`."""
import sys

from .cli import main

sys.exit(main())
