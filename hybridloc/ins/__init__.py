"""Foot-mounted inertial navigation: strapdown, 15-state error-state EKF, stance detectors."""
