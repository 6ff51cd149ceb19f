"""Pipeline: samples in, fused estimates out, for one target (above filters, calibration and margin).

``synchronizer`` (pairing and ordering by stamp) under ``stamp_rules`` (duplicate / late / timeline restart),
``frame_chain`` (device poses -> the target in ``base``), ``sources`` (which topics feed a target), ``target``
(TargetConfig, FusedOutput), ``measure`` (an item's samples as the filters' measurements), ``lane`` (filters fused
together and their state: what a rewind restores), ``problems`` (counters and reasons), ``ordered`` (TargetPipeline:
fuse in stamp order) and ``arrival`` (fuse on arrival, rewind a late sample; its ``history`` and ``link_views``).
The nodes at the top of fullperc_fusion are thin wrappers of these.
"""
