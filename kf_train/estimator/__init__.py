"""Floor 3, the streaming estimator: stamped measurements in, estimates out."""
