"""``python -m fullperc_eval.bag info|reindex BAG`` (see :mod:`.cli`)."""

import sys

from .cli import main

sys.exit(main())
