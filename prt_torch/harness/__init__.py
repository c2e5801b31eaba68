"""prt_torch.harness — metrics, timing, sweeps, result files, tables and plots."""
