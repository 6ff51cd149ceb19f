"""Offline evaluation: replay a bag through the fusion pipeline, compare with the arm's ground truth, report.

Layer: above :mod:`fullperc_eval.sim` (it may import sim, bag, emulators and every other package), below
:mod:`fullperc_eval.graph`. Modules, each importing only the ones before it:

* :mod:`.config` -- the methods (:data:`~.config.METHODS`) and fusion_node's parameters as a TargetConfig;
* :mod:`.ground_truth` -- the target's true pose from the joint states and the bag's calibration;
* :mod:`.sources` -- a tap on the measurements the filters get (the raw local chain as a single source);
* :mod:`.replay` -- a bag's raw topics through the pipeline as ``fusion_node`` runs it (or its live outputs);
* :mod:`.orientation`, :mod:`.consistency` -- orientation error [deg], pose-error vectors, NEES;
* :mod:`.headline` -- region definitions, the OMC's hops, the report's one-paragraph headline;
* :mod:`.metrics` -- Table 1 / Table 2 figures of one replay; :func:`~.metrics.evaluate_bag`;
* :mod:`.tables` -- the tables as text, results as JSON;
* :mod:`.report` -- plots and an HTML page (matplotlib, imported lazily);
* :mod:`.accuracy`, :mod:`.accuracy_goals` -- ``make accuracy`` over seeds and profiles, the issue-18 goals;
* :mod:`.cli` -- the ``evaluate`` executable; :mod:`.evaluate_all` -- ``make eval`` over a directory of bags.
"""
