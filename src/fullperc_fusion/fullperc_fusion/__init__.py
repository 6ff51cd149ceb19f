"""Estimation: frame chain, KF/BKF/CKF/CBKF filters, synchronizer, view-margin model; fusion_node and margin_node."""
