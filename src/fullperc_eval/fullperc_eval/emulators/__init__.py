"""Device emulators that speak the real protocols: the NDI Polaris Vega (Combined API on TCP and a pty).

Layer: the bottom of ``fullperc_eval`` beside :mod:`fullperc_eval.bag` (neither imports the other); it imports
``fullperc_drivers`` (the NDI protocol core), ``fullperc_fusion`` (the margin model's measurement volume) and
``fullperc_common``. :mod:`.vega_device` is the device, :mod:`.vega_server` its links, :mod:`.vega_cli` the
``vega_emulator`` executable.
"""
