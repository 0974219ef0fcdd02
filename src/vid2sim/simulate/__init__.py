"""New simulations of an asset: scenarios (materials, floors, obstacles, views), their runs and outputs."""
