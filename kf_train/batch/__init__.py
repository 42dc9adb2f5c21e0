"""Floor 3, batch paths: vectorised series, banks, fleets and the RTS smoother."""
