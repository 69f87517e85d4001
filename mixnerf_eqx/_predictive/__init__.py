"""The predictive distribution of a ray's colour and depth, and its calibration."""
