"""State estimation: an extended Kalman filter with disturbance states."""
