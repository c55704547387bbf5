"""Measurement: ePSF building, forced PSF fitting, cross-matching, proper
motions and accuracy reports."""
