"""The benchmark core every layer shares: the contract a benchmark satisfies (:mod:`bpp.core.contract`), the registry
that finds one by name (:mod:`bpp.core.registry`), prompted rollouts (:mod:`bpp.core.prompting`) and rigid poses for
6-DoF actions (:mod:`bpp.core.poses`). The benchmarks themselves live in :mod:`bpp.benchmarks`, one folder each."""
