"""Device drivers: NDI Combined API (Vega TCP, Spectra/Vicra serial), NOKOV motion capture, Diana 7 arm state."""
