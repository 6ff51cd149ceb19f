"""Start-up cost: a process start imports its node's modules, and the suite and a launch start many."""

from __future__ import annotations

import subprocess
import sys


def test_node_processes_do_not_import_what_they_do_not_use():
    """Start-up cost: every process start imports its modules (a suite starts hundreds). The drivers convert poses
    without scipy (transforms imports Rotation where a batch or fallback needs it; diana_state only for the
    controller's TCP of its diana_api backend) and fusion_node does not import scipy.stats (~0.6 s here)."""
    code = ("import sys, importlib; importlib.import_module(sys.argv[1]); "
            "print(' '.join(m for m in ('scipy.stats', 'scipy.spatial', 'matplotlib', 'rosbags') if m in sys.modules))")
    for module, allowed in (("fullperc_drivers.ndi_driver", set()), ("fullperc_drivers.omc_driver", set()),
                            ("fullperc_drivers.diana_state", set()),
                            ("fullperc_fusion.fusion_node", {"scipy.spatial"}),
                            ("fullperc_eval.evaluation.cli", {"scipy.spatial"})):
        out = subprocess.run([sys.executable, "-c", code, module], capture_output=True, text=True, check=True)
        assert set(out.stdout.split()) <= allowed, (module, out.stdout)


def test_fusion_nodes_health_imports_the_stamp_offset_fit_at_its_first_estimate():
    """fusion_node's start builds a TargetHealth per target; its stamp-offset watch needs scipy.signal (and through
    it scipy.stats, ~0.4 s of CPU) only for an estimate, after ``offset_period_s`` of samples."""
    code = ("import sys; import numpy as np; from fullperc_fusion.fusion_health import TargetHealth; "
            "h = TargetHealth('tool', {}, background=False); print('scipy.signal' in sys.modules); "
            "w = h.offset; w._fit(np.linspace(0, 1, 30), np.zeros((30, 3)), np.linspace(0, 1, 30), np.zeros((30, 3))); "
            "print('scipy.signal' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "True"], out


def test_rosbags_yaml_has_its_c_loader():
    """rosbags parses metadata.yaml and each MCAP channel's QoS with ruamel.yaml; without ruamel.yaml.clib (optional
    since ruamel.yaml 0.19, requirements/python.txt pins it) every bag open costs ~0.45 s more."""
    from ruamel.yaml import YAML

    assert YAML(typ="safe").Parser.__name__ == "CParser"   # the pure-Python one is ruamel.yaml.parser.Parser
