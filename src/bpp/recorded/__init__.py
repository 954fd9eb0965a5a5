"""What the benchmarks of recorded demonstrations share (imported LeRobot datasets, :mod:`bpp.benchmarks.lerobot`;
iPhUMI phone recordings, :mod:`bpp.benchmarks.iphumi`): there is no simulator, so a policy is evaluated open loop on
held-out recorded episodes (:mod:`~bpp.recorded.replay`, :mod:`~bpp.recorded.heldout`), and the part of the contract
that follows from that (:class:`~bpp.recorded.benchmark.RecordedDemonstrations`)."""
