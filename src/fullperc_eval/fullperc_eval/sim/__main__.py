"""``python -m fullperc_eval.sim --write-plans``: regenerate the shipped task plans (see :mod:`.tasks`)."""

import sys

from .tasks import main

sys.exit(main())
