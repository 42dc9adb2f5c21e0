"""Floor 1, the filter mathematics: numpy only (Kalman, models, EKF, UKF, particle, χ²)."""
