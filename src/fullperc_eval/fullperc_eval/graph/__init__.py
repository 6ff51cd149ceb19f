"""Process graphs: the supervisor that runs a YAML graph of executables, and the simulated-OR demo.

Layer: the top of ``fullperc_eval``; it may import every other sub-package (the demo evaluates what it
recorded), nothing imports it. :mod:`.supervisor` runs a graph, :mod:`.demo` the demo graph and its
evaluation, :mod:`.cli` is the ``supervisor`` executable (``run`` / ``demo``).
"""
