"""Scene folders, video I/O and the synthetic benchmark generator."""
