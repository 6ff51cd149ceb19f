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
                            ("fullperc_fusion.fusion_node", {"scipy.spatial"}), ("fullperc_fusion.margin_node", set()),
                            ("fullperc_eval.evaluation.cli", {"scipy.spatial"})):
        out = subprocess.run([sys.executable, "-c", code, module], capture_output=True, text=True, check=True)
        assert set(out.stdout.split()) <= allowed, (module, out.stdout)


def test_fusion_nodes_stamp_offset_fit_needs_neither_scipy_signal_nor_scipy_stats():
    """fusion_node's start builds a TargetHealth per target, whose stamp-offset watch imports time_offset then (an
    import at the first estimate would hold up the input thread): its fit runs on scipy.fft, interpolate and
    optimize, not scipy.signal, whose import brings scipy.stats (~0.35 s of CPU per node start, 1 s cold)."""
    code = ("import sys; import numpy as np; from fullperc_fusion.fusion_health import TargetHealth; "
            "h = TargetHealth('tool', {}, background=False); "
            "print('fullperc_fusion.calibration.time_offset' in sys.modules); "
            "t = np.arange(0, 12, 0.01); p = np.stack([np.sin(2 * t), np.cos(3 * t), 0 * t], 1) * 0.1; "
            "h.offset._fit(t, p, t[::2] + 0.01, p[::2]); "
            "print(' '.join(m for m in ('scipy.signal', 'scipy.stats') if m in sys.modules) or 'neither')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["True", "neither"], out


def test_margin_nodes_layout_is_read_without_scipy():
    """margin_node's start reads the OR layout (camera orientations as quaternions): transforms' closed form, which is
    scipy's ``from_quat().as_matrix()`` bit for bit (test_transforms_closed_form.py), spares it scipy.spatial's
    import (~0.25 s of CPU per start)."""
    code = ("import sys; from fullperc_fusion.margin.layout import default_layout_path, load_layout; "
            "lay = load_layout(default_layout_path()); print(len(lay.cameras) > 0, 'scipy.spatial' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["True", "False"], out


def test_rosbags_yaml_has_its_c_loader():
    """rosbags parses metadata.yaml and each MCAP channel's QoS with ruamel.yaml; without ruamel.yaml.clib (optional
    since ruamel.yaml 0.19, requirements/python.txt pins it) every bag open costs ~0.45 s more."""
    from ruamel.yaml import YAML

    assert YAML(typ="safe").Parser.__name__ == "CParser"   # the pure-Python one is ruamel.yaml.parser.Parser
