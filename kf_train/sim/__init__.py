"""Floor 3, simulation: truth, seed scenarios, streams, faults and baselines."""
