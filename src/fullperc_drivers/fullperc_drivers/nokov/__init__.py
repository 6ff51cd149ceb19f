"""NOKOV (XINGYING) optical motion capture: frame model, vendor-SDK (ctypes) and simulator-stream backends."""
