"""Star measurement: ePSF building, detection, PSF fitting, errors and accuracy reports."""
