"""Applications built on the layers: the benchmarks and suites (:mod:`vid2sim.apps.bench`) and the demo
(:mod:`vid2sim.apps.demo`)."""
