"""Pipeline: samples in, fused estimates out, for one target (above filters, calibration and margin).

``synchronizer`` (pairing and ordering by stamp), ``frame_chain`` (device poses -> the target in ``base``),
``sources`` (which topics feed a target), ``ordered`` (TargetPipeline: fuse in stamp order) and ``arrival`` (fuse on
arrival, rewind a late sample). The nodes at the top of fullperc_fusion are thin wrappers of these.
"""
