"""Pieces every fullperc package shares, so drivers, fusion and eval agree on conventions.

``transforms`` is pure numpy/scipy (no ROS); ``ros_conv``, ``diagnostics`` and ``params``
import ROS message types and are used only by the thin node layers.
"""
