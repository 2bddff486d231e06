"""Calibration of the Sm pipe-wall models and model selection by AIC."""
