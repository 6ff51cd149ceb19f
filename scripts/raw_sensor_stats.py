"""Source-checkout entry of ``fit_noise_model`` (:mod:`fullperc_eval.evaluation.sensor_stats`), kept for the
commands of docs/fullperc_filter.md and for the scripts beside it that use its rows
(``from raw_sensor_stats import bag_rows``).

Run: python scripts/raw_sensor_stats.py bags/spec bags/paper [--write noise.yaml]
"""

import sys

from fullperc_eval.evaluation.sensor_stats import *  # noqa: F403 - re-exported for omc_lens_fit.py & co.
from fullperc_eval.evaluation.sensor_stats import main

if __name__ == "__main__":
    sys.exit(main())
