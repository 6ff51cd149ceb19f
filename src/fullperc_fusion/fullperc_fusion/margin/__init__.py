"""Margin: the OR layout and the paper's view-margin model (a layer below the pipeline; not estimation).

``geometry`` (cameras, the tracker's volume, occluders), ``layout`` (the layout file: the room and its devices),
``view_margin`` (the margin of a point), ``map`` (margin heat maps) and ``hysteresis`` (the region label with
hysteresis, ``margin_node``'s; not a Kalman filter). Imports nothing else of fullperc_fusion.
"""
