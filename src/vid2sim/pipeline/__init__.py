"""Stage II orchestration: reconstruct a scene folder into a simulation-ready asset."""
