"""The drivers' reliable history holds more than a heartbeat period of samples (config/diana.yaml says why).

A reliable subscriber that missed samples (a stall on a busy machine) asks for them after the writer's next
heartbeat -- Fast DDS sends one every 3 s -- and gets back only what is still in the writer's KEEP_LAST history.
With 10 the demo's recorder lost runs of joint states, and with them the ground truth of those stamps.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1]
HEARTBEAT_S = 3.0          # Fast DDS WriterTimes.heartbeat_period default
# the highest rate each driver publishes at in our setups [Hz]: the twin's Diana stream, NOKOV at 240 Hz, the
# Vega at up to 400 Hz (NDI polling of the emulator), the Spectra at 60 Hz
CASES = [("diana.yaml", "diana_state.py", 100.0), ("omc.yaml", "omc_driver.py", 240.0),
         ("ndi_vega.yaml", "ndi_driver.py", 400.0), ("ndi_spectra.yaml", "ndi_driver.py", 60.0)]


def _yaml_depth(name: str) -> int:
    m = re.search(r"^\s+qos_depth:\s*(\d+)", (PKG / "config" / name).read_text(), re.M)
    assert m, f"{name} sets no qos_depth"
    return int(m.group(1))


def _code_default(module: str) -> int:
    m = re.search(r'declare(?:_fixed)?\(self, "qos_depth", (\d+),', (PKG / "fullperc_drivers" / module).read_text())
    assert m, f"{module} declares no qos_depth"
    return int(m.group(1))


@pytest.mark.parametrize("config, module, rate_hz", CASES, ids=[c[0] for c in CASES])
def test_reliable_history_outlasts_a_heartbeat(config, module, rate_hz):
    depth = _yaml_depth(config)
    assert depth / rate_hz > HEARTBEAT_S, f"{config}: qos_depth {depth} is {depth / rate_hz:.2f} s at {rate_hz} Hz"
    assert _code_default(module) / rate_hz > HEARTBEAT_S, f"{module}: the node's own default is too small"
