"""Calibration: static links between the devices' frames, estimated from sightings (a layer below the pipeline).

``se3_stats`` (robust SE(3) means, covariances, gates), ``poses`` (sample validation), ``run`` (one collection),
``io`` (calibration YAML) and ``monitor`` (a link that moved). Imports neither filters nor margin nor pipeline.
"""
