"""What the evaluator runs and with which configuration: the methods, and fusion_node's parameters.

The offline replay must run the filters exactly as ``fusion_node`` does, so the configuration comes from the
node's own params file (``fullperc_fusion/config/fusion.yaml`` by default) through the node's own mapping,
:func:`fullperc_fusion.fusion_config.load_fusion_config`; :func:`replay_config` only adds what the evaluator
needs on top: every method side by side, and its own error type.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from fullperc_fusion.fusion_config import FusionConfigError, load_fusion_config
from fullperc_fusion.pipeline.ordered import FILTER_NAMES, TargetConfig

# Every method: the paper's five in the paper's column order (Table 1: OMC, KF, BKF, CKF, CBKF) first, then every
# further registered filter (e.g. fullperc) in registry order -- so the paper's tables, JSON lines and figures keep
# their columns wherever a new filter is registered, and a new filter shows up everywhere without another list.
PAPER_METHODS: tuple[str, ...] = ("omc", "kf", "bkf", "ckf", "cbkf")
METHODS: tuple[str, ...] = (tuple(m for m in PAPER_METHODS if m in FILTER_NAMES)
                            + tuple(m for m in FILTER_NAMES if m not in PAPER_METHODS))


class EvaluationError(Exception):
    """The bag or its companions cannot be evaluated; the message says why."""


def replay_config(path: str | Path | None = None, target: str = "tool") -> tuple[TargetConfig, dict[str, Any]]:
    """fusion_node's TargetConfig of ``target`` running every method of :data:`METHODS`, and the parameter values.

    ``path`` None: the installed (else source) ``fullperc_fusion/config/fusion.yaml``. The values hold every
    parameter as used (defaults filled in) and ``_source``, the file. A file that cannot be read or holds a wrong
    value raises :class:`EvaluationError` naming the file and the parameter.
    """
    try:
        config, values = load_fusion_config(path, target, filters=METHODS)
    except FusionConfigError as e:
        raise EvaluationError(str(e)) from None
    if values.get("clock", "stamps") != "stamps":
        print(f"note: fusion config clock '{values['clock']}' is a live setting; offline evaluation always runs on "
              "the stamps (the default)", file=sys.stderr)
    return config, values
