"""Calibration: static links between the devices' frames, estimated from sightings (a layer below the pipeline).

``se3_stats`` (robust SE(3) means with covariance, the links' data), ``static_check`` (did a body move during a
collection), ``links`` (the three links from sightings), ``collector`` (one collection's sightings -> a
Calibration), ``static_links`` (a target chain's links from the start of a run to every re-estimation),
``poses`` (sample validation), ``run`` (one collection bounded in host time), ``io`` (calibration YAML) and
``monitor`` (a link that moved). Imports neither filters nor margin nor pipeline.
"""
