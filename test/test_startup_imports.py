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


def test_rosbags_yaml_has_its_c_loader():
    """rosbags parses metadata.yaml and each MCAP channel's QoS with ruamel.yaml; without ruamel.yaml.clib (optional
    since ruamel.yaml 0.19, requirements/python.txt pins it) every bag open costs ~0.45 s more."""
    from ruamel.yaml import YAML

    assert YAML(typ="safe").Parser.__name__ == "CParser"   # the pure-Python one is ruamel.yaml.parser.Parser
